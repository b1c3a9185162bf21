//! The encoder's planet transform: analysis, parallel synthesis, and the encoder's needs
//! (distinct points, nodata filling) of the cube raster placed in the sphere hierarchy,
//! [`SphereGeometry`] from `quincunx-decoder` (its module documents the storage, units,
//! levels and roots).

use rayon::prelude::*;

use crate::raster::{
    EncodeLayout, RasterError, Transform, analyze_levels, check_len, synthesize_par_checked,
};
#[doc(inline)]
pub use quincunx_decoder::sphere_raster::{Kids, SphereFrame, SphereGeometry, SphereSlot};

impl Transform for SphereGeometry {
    fn analyze(&self, raster: &mut [i32]) -> Result<Vec<Vec<Vec<i32>>>, RasterError> {
        self.make_consistent(raster)?;
        check_len(self, raster)?;
        Ok(analyze_levels(self, raster))
    }

    fn synthesize_par<F, R>(
        &self,
        raster: &mut [i32],
        details: &[Vec<Vec<i32>>],
        visit: F,
    ) -> Result<Vec<Vec<R>>, RasterError>
    where
        F: Fn(usize, usize, &[i32], &[i32], &[i32]) -> R + Sync,
        R: Send,
    {
        synthesize_par_checked(self, raster, details, visit)
    }
}

impl EncodeLayout for SphereGeometry {
    fn clear_duplicates(&self, mask: &mut [bool]) {
        // Only points on a face's border have other copies: per row, its two ends, or all
        // of it on the face's first and last rows.
        let w = self.width();
        mask.par_chunks_mut(w)
            .enumerate()
            .for_each(|(row, entries)| {
                let v = row % w;
                let (start, last) = (row * w, entries.len() - 1);
                let mut check = |u: usize| {
                    if entries[u] && !self.is_canonical(start + u) {
                        entries[u] = false;
                    }
                };
                if v == 0 || v + 1 == w {
                    (0..=last).for_each(&mut check);
                } else {
                    check(0);
                    check(last);
                }
            });
    }

    fn distinct_len(&self) -> usize {
        self.distinct_points()
    }

    fn fill_nodata(
        &self,
        values: &[f64],
        valid: &[bool],
        out: &mut [i32],
        to_int: &(dyn Fn(f64) -> i32 + Sync),
    ) -> bool {
        // Summed in order: a parallel reduction would make the mean, and so the
        // repository's bytes, depend on how the work was split.
        let (sum, count) = values
            .iter()
            .zip(valid)
            .filter(|(_, b)| **b)
            .fold((0.0, 0usize), |(s, c), (&x, _)| (s + x, c + 1));
        if count == 0 {
            return false;
        }
        let mean = sum / count as f64;
        let w = self.width();
        out.par_chunks_exact_mut(w * w)
            .zip(values.par_chunks_exact(w * w))
            .zip(valid.par_chunks_exact(w * w))
            .for_each(|((out, face), ok)| {
                if !crate::fill::fill_into(w, w, face, ok, out, to_int) {
                    out.iter_mut().for_each(|x| *x = to_int(mean));
                }
            });
        self.make_consistent(out).is_ok()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn every_slot_index_is_a_copy_of_its_sample_position() {
        for (face_side, n) in [(8, 8), (16, 4), (32, 8), (64, 8)] {
            let g = SphereGeometry::new(face_side, n).unwrap();
            let d = g.domain();
            let two_n = 2 * n as i64;
            let all = g
                .root_slots()
                .iter()
                .chain((0..g.detail_levels()).flat_map(|l| g.level(l)));
            let mut checked = 0;
            for s in all {
                for i in 0..=n {
                    for j in 0..=n {
                        let p = d.vertex_position(s.id, n, i, j).unwrap().map(|x| x / two_n);
                        let copies: Vec<usize> = g.point_indices(p).collect();
                        assert!(
                            copies.contains(&s.vertex_index(i, j)),
                            "{face_side}/{n} {:?} vertex ({i},{j})",
                            s.id
                        );
                        if s.is_edge() && i == j && 0 < i && i < n {
                            assert_eq!(s.vertex_index(i, j), copies[0], "diagonal");
                        }
                        // Cells are samples only in diamonds that carry details.
                        if i < n && j < n && g.detail_levels() > 0 {
                            let p = d.cell_position(s.id, n, i, j).unwrap();
                            assert!(p.iter().all(|x| x % two_n == 0), "cell off the samples");
                            let copies: Vec<usize> =
                                g.point_indices(p.map(|x| x / two_n)).collect();
                            assert_eq!(s.cell_index(i, j), copies[0]);
                        }
                        checked += 1;
                    }
                }
            }
            assert!(checked > 0);
        }
    }

    #[test]
    fn finest_cells_and_roots_cover_every_point_once_per_level() {
        let (face_side, n) = (32, 4);
        let g = SphereGeometry::new(face_side, n).unwrap();
        assert_eq!(g.detail_levels(), 6);
        let mut hit = vec![0u32; g.cube_len()];
        for l in 0..g.detail_levels() {
            for s in g.level(l) {
                for i in 0..n {
                    for j in 0..n {
                        hit[s.cell_index(i, j)] += 1;
                    }
                }
            }
        }
        for s in g.root_slots() {
            for i in 0..=n {
                for j in 0..=n {
                    let k = s.vertex_index(i, j);
                    hit[k] += u32::from(g.is_canonical(k));
                }
            }
        }
        // Every distinct point is a root vertex or a cell of exactly one diamond (cells of
        // consecutive levels are the new lattice points).
        let mut distinct = 0;
        for (k, &h) in hit.iter().enumerate() {
            if g.is_canonical(k) {
                distinct += 1;
                assert_eq!(h, 1, "point {k}");
            } else {
                assert_eq!(h, 0);
            }
        }
        assert_eq!(distinct, g.distinct_points());
    }

    #[test]
    fn clearing_duplicates_keeps_exactly_the_canonical_copies() {
        for (face_side, n) in [(8, 8), (32, 4), (64, 16)] {
            let g = SphereGeometry::new(face_side, n).unwrap();
            let mut mask = vec![true; g.cube_len()];
            // Entries already cleared stay cleared.
            mask[7] = false;
            g.clear_duplicates(&mut mask);
            for (k, &m) in mask.iter().enumerate() {
                assert_eq!(m, k != 7 && g.is_canonical(k), "{face_side} {n}: entry {k}");
            }
            let kept = mask.iter().filter(|&&m| m).count();
            assert_eq!(kept + usize::from(g.is_canonical(7)), g.distinct_points());
        }
    }

    #[test]
    fn analysis_and_synthesis_round_trip_with_consistent_copies() {
        for (face_side, n) in [(8, 8), (32, 4), (64, 16)] {
            let g = SphereGeometry::new(face_side, n).unwrap();
            let mut orig: Vec<i32> = (0..g.cube_len())
                .map(|k| ((k * 2654435761) % 1013) as i32 - 300)
                .collect();
            g.make_consistent(&mut orig).unwrap();
            let mut r = orig.clone();
            let details = g.analyze(&mut r).unwrap();
            let roots = g.gather_roots(&r);
            let mut out = vec![0; g.cube_len()];
            g.scatter_roots(&roots, &mut out).unwrap();
            g.synthesize::<RasterError>(&mut out, |l, i, h| {
                h.copy_from_slice(&details[l][i]);
                Ok(true)
            })
            .unwrap();
            assert_eq!(out, orig, "{face_side} N={n}");
        }
    }

    #[test]
    fn bad_face_sides_are_rejected() {
        assert!(SphereGeometry::new(48, 16).is_err());
        assert!(SphereGeometry::new(8, 16).is_err());
        assert!(SphereGeometry::new(2, 2).is_err());
        assert!(SphereGeometry::new(0, 4).is_err());
        assert!(SphereGeometry::new(64, 3).is_err());
        assert!(SphereGeometry::new(4, 2).is_ok());
    }
}

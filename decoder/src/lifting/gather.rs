//! Gather/scatter between a refined diamond's lattice and its children's halves.
//!
//! After synthesis, a diamond's updated vertices and its cell centres form the next
//! level's lattice inside its square. Each child owns half of that lattice (the triangle
//! on its side of the parent's hypotenuse... of the shared side), in the child's own
//! frame. The map between child vertex indices and parent lattice indices is affine with
//! coefficients in {-1, 0, 1}, computed from the two frames (corners `[E1, P1, E2, P2]`
//! expressed in one common 2D chart, id units).

/// Affine map from child vertex `(i, j)` to the parent's doubled lattice coordinates
/// `(p, q)`: vertex `(a, b)` of the parent is `(2a, 2b)`, cell `(a, b)` is `(2a+1, 2b+1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GridMap {
    p0: i64,
    q0: i64,
    dpi: i64,
    dqi: i64,
    dpj: i64,
    dqj: i64,
}

impl GridMap {
    /// Parent lattice coordinates of child vertex `(i, j)`.
    pub fn map(&self, i: usize, j: usize) -> (i64, i64) {
        let (i, j) = (i as i64, j as i64);
        (
            self.p0 + i * self.dpi + j * self.dpj,
            self.q0 + i * self.dqi + j * self.dqj,
        )
    }
}

fn sub(a: [i64; 2], b: [i64; 2]) -> [i64; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

fn dot(a: [i64; 2], b: [i64; 2]) -> i128 {
    a[0] as i128 * b[0] as i128 + a[1] as i128 * b[1] as i128
}

/// The map from `child`'s vertex grid to `parent`'s refined lattice, or `None` when the
/// frames are not parent and child (their lattices do not line up).
pub fn child_half(parent: &[[i64; 2]; 4], child: &[[i64; 2]; 4], n: usize) -> Option<GridMap> {
    let big_a = sub(parent[1], parent[0]);
    let big_b = sub(parent[3], parent[0]);
    let la = dot(big_a, big_a);
    let lb = dot(big_b, big_b);
    if la == 0 || lb == 0 || la != lb || dot(big_a, big_b) != 0 {
        return None;
    }
    let n = n as i128;
    // Parent point (p, q) = 2N E1 + p A + q B (sample units); child vertex (i, j) =
    // 2N E1' + 2 i A' + 2 j B'. Project onto A and B.
    let proj = |x: [i128; 2]| -> Option<(i64, i64)> {
        let pa = x[0] * big_a[0] as i128 + x[1] * big_a[1] as i128;
        let pb = x[0] * big_b[0] as i128 + x[1] * big_b[1] as i128;
        if pa % la != 0 || pb % lb != 0 {
            return None;
        }
        Some(((pa / la) as i64, (pb / lb) as i64))
    };
    let d0 = sub(child[0], parent[0]);
    let (p0, q0) = proj([2 * n * d0[0] as i128, 2 * n * d0[1] as i128])?;
    let ca = sub(child[1], child[0]);
    let cb = sub(child[3], child[0]);
    let (dpi, dqi) = proj([2 * ca[0] as i128, 2 * ca[1] as i128])?;
    let (dpj, dqj) = proj([2 * cb[0] as i128, 2 * cb[1] as i128])?;
    if [dpi, dqi, dpj, dqj].iter().any(|d| d.abs() > 1) {
        return None;
    }
    Some(GridMap {
        p0,
        q0,
        dpi,
        dqi,
        dpj,
        dqj,
    })
}

/// Copies the part of the parent's refined lattice (`v`: updated vertices, `c`: cell
/// centres) that lies in the child into the child's vertex grid `child_v`; marks the
/// written entries in `written` when given. Returns the number of vertices written.
pub fn scatter_to_child(
    map: &GridMap,
    n: usize,
    v: &[i32],
    c: &[i32],
    child_v: &mut [i32],
    mut written: Option<&mut [bool]>,
) -> usize {
    let w = n + 1;
    let two_n = 2 * n as i64;
    let last = n as i64;
    let mut count = 0;
    // Along a row, p and q are affine in j with slopes in {-1, 0, 1}: the entries that
    // land on the parent's lattice form one interval of j, every or every other entry.
    let range = |base: i64, slope: i64| -> (i64, i64) {
        match slope {
            0 if (0..=two_n).contains(&base) => (0, last),
            0 => (1, 0),
            1 => (-base, two_n - base),
            _ => (base - two_n, base),
        }
    };
    for i in 0..=n {
        let (a, b) = map.map(i, 0);
        let (pa, pb) = range(a, map.dpj);
        let (qa, qb) = range(b, map.dqj);
        let mut lo = pa.max(qa).max(0);
        let hi = pb.min(qb).min(last);
        let step = if (map.dpj - map.dqj) % 2 == 0 {
            if (a - b) % 2 != 0 {
                continue;
            }
            1
        } else {
            // p - q changes parity with j: start where it is even.
            if (a - b + lo).rem_euclid(2) != 0 {
                lo += 1;
            }
            2
        };
        let mut j = lo;
        while j <= hi {
            let (p, q) = (a + j * map.dpj, b + j * map.dqj);
            let value = if p % 2 == 0 {
                v[(p / 2) as usize * w + (q / 2) as usize]
            } else {
                c[(p / 2) as usize * n + (q / 2) as usize]
            };
            let at = i * w + j as usize;
            child_v[at] = value;
            if let Some(wr) = written.as_deref_mut() {
                wr[at] = true;
            }
            count += 1;
            j += step;
        }
    }
    count
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    /// The definition: every child entry whose image is on the parent's lattice.
    fn naive(map: &GridMap, n: usize, v: &[i32], c: &[i32], out: &mut [i32], wr: &mut [bool]) {
        let (w, two_n) = (n + 1, 2 * n as i64);
        for i in 0..=n {
            for j in 0..=n {
                let (p, q) = map.map(i, j);
                if !(0..=two_n).contains(&p) || !(0..=two_n).contains(&q) || (p - q) % 2 != 0 {
                    continue;
                }
                out[i * w + j] = if p % 2 == 0 {
                    v[(p / 2) as usize * w + (q / 2) as usize]
                } else {
                    c[(p / 2) as usize * n + (q / 2) as usize]
                };
                wr[i * w + j] = true;
            }
        }
    }

    #[test]
    fn the_row_intervals_scatter_exactly_what_the_definition_does() {
        let n = 8usize;
        let w = n + 1;
        let v: Vec<i32> = (0..(w * w) as i32).collect();
        let c: Vec<i32> = (0..(n * n) as i32).map(|x| 1000 + x).collect();
        let slopes = [-1i64, 0, 1];
        let mut maps = 0;
        for dpi in slopes {
            for dqi in slopes {
                for dpj in slopes {
                    for dqj in slopes {
                        for p0 in [
                            -2 * n as i64,
                            -3,
                            0,
                            1,
                            n as i64,
                            2 * n as i64,
                            3 * n as i64,
                        ] {
                            for q0 in [-1i64, 0, 2, n as i64 + 1, 2 * n as i64] {
                                let map = GridMap {
                                    p0,
                                    q0,
                                    dpi,
                                    dqi,
                                    dpj,
                                    dqj,
                                };
                                let (mut a, mut wa) = (vec![-1; w * w], vec![false; w * w]);
                                let (mut b, mut wb) = (vec![-1; w * w], vec![false; w * w]);
                                naive(&map, n, &v, &c, &mut a, &mut wa);
                                let count =
                                    scatter_to_child(&map, n, &v, &c, &mut b, Some(&mut wb));
                                assert_eq!((a, wa.clone()), (b, wb), "{map:?}");
                                assert_eq!(count, wa.iter().filter(|&&x| x).count());
                                maps += 1;
                            }
                        }
                    }
                }
            }
        }
        assert_eq!(maps, 81 * 35);
    }
}

//! Smooth filling of nodata samples (push-pull), so holes create no spikes or cliffs.
//!
//! Valid samples are averaged down a pyramid of half-resolution levels; holes are then
//! filled from the coarser level by bilinear interpolation, coarse to fine. Filled values
//! are smooth continuations of their surroundings, which also makes them cheap to code.

/// Fills `values[k]` where `valid[k]` is false. Returns `false` if no sample is valid.
pub fn push_pull(width: usize, height: usize, values: &mut [f64], valid: &[bool]) -> bool {
    if !valid.iter().any(|&v| v) {
        return false;
    }
    if valid.iter().all(|&v| v) {
        return true;
    }
    // Pyramid of (weighted sum, weight), starting at half resolution.
    let mut levels: Vec<(usize, usize, Vec<f64>, Vec<f64>)> = Vec::new();
    let (mut w, mut h) = (width, height);
    {
        let (w2, h2) = (w.div_ceil(2), h.div_ceil(2));
        let mut s2 = vec![0.0; w2 * h2];
        let mut wt2 = vec![0.0; w2 * h2];
        for y in 0..h {
            for x in 0..w {
                let k = y * w + x;
                if valid[k] {
                    let k2 = (y / 2) * w2 + x / 2;
                    s2[k2] += values[k];
                    wt2[k2] += 1.0;
                }
            }
        }
        levels.push((w2, h2, s2, wt2));
        (w, h) = (w2, h2);
    }
    while w > 1 || h > 1 {
        let (_, _, s, wt) = &levels[levels.len() - 1];
        let (w2, h2) = (w.div_ceil(2), h.div_ceil(2));
        let mut s2 = vec![0.0; w2 * h2];
        let mut wt2 = vec![0.0; w2 * h2];
        for y in 0..h {
            for x in 0..w {
                let k2 = (y / 2) * w2 + x / 2;
                s2[k2] += s[y * w + x];
                wt2[k2] += wt[y * w + x];
            }
        }
        levels.push((w2, h2, s2, wt2));
        (w, h) = (w2, h2);
    }
    // Coarse to fine: a level's value is its mean where it has weight, else the
    // bilinear interpolation of the (already filled) coarser level.
    let mut coarse: Vec<f64> = Vec::new();
    let mut coarse_dims = (0usize, 0usize);
    for (w, h, s, wt) in levels.iter().rev() {
        let mut out = vec![0.0; w * h];
        for y in 0..*h {
            for x in 0..*w {
                let k = y * w + x;
                out[k] = if wt[k] > 0.0 {
                    s[k] / wt[k]
                } else {
                    sample_bilinear(
                        &coarse,
                        coarse_dims,
                        (x as f64 + 0.5) / 2.0 - 0.5,
                        (y as f64 + 0.5) / 2.0 - 0.5,
                    )
                };
            }
        }
        coarse = out;
        coarse_dims = (*w, *h);
    }
    for y in 0..height {
        for x in 0..width {
            let k = y * width + x;
            if !valid[k] {
                values[k] = sample_bilinear(
                    &coarse,
                    coarse_dims,
                    (x as f64 + 0.5) / 2.0 - 0.5,
                    (y as f64 + 0.5) / 2.0 - 0.5,
                );
            }
        }
    }
    true
}

fn sample_bilinear(img: &[f64], (w, h): (usize, usize), x: f64, y: f64) -> f64 {
    let x = x.clamp(0.0, (w - 1) as f64);
    let y = y.clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let top = img[y0 * w + x0] * (1.0 - fx) + img[y0 * w + x1] * fx;
    let bottom = img[y1 * w + x0] * (1.0 - fx) + img[y1 * w + x1] * fx;
    top * (1.0 - fy) + bottom * fy
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn holes_are_filled_within_the_range_of_their_surroundings() {
        let (w, h) = (40, 30);
        let mut v: Vec<f64> = (0..w * h)
            .map(|k| (k % w) as f64 * 2.0 + (k / w) as f64)
            .collect();
        let valid: Vec<bool> = (0..w * h)
            .map(|k| !((10..20).contains(&(k % w)) && (5..15).contains(&(k / w))))
            .collect();
        for (k, x) in v.iter_mut().enumerate() {
            if !valid[k] {
                *x = -32768.0;
            }
        }
        assert!(push_pull(w, h, &mut v, &valid));
        for &x in &v {
            assert!((0.0..=120.0).contains(&x), "{x}");
        }
    }
}

//! YCoCg-R: the reversible (lossless, integer) RGB <-> luma/chroma transform used for colour
//! repositories (Malvar and Sullivan, "YCoCg-R: a colour space with RGB reversibility and
//! low dynamic range", JVT-I014, 2003).
//!
//! For 8-bit RGB, `Y` lies in `0..=255` and `Co`, `Cg` in `-255..=255`. Each channel is then
//! coded like a height field; decorrelating the channels first concentrates the energy in
//! `Y`, so the chroma channels cost far fewer bits at any tolerance.

/// Forward transform of one pixel: `(Y, Co, Cg)`. Exactly inverted by [`ycocg_r_to_rgb`]
/// for every `i32` triple whose intermediate sums do not overflow (any 8- to 16-bit input).
#[inline]
pub fn rgb_to_ycocg_r(r: i32, g: i32, b: i32) -> (i32, i32, i32) {
    let co = r - b;
    let t = b + (co >> 1);
    let cg = g - t;
    let y = t + (cg >> 1);
    (y, co, cg)
}

/// Inverse of [`rgb_to_ycocg_r`]: `(R, G, B)`.
#[inline]
pub fn ycocg_r_to_rgb(y: i32, co: i32, cg: i32) -> (i32, i32, i32) {
    let t = y - (cg >> 1);
    let g = cg + t;
    let b = t - (co >> 1);
    let r = b + co;
    (r, g, b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_8_bit_colour_round_trips_exactly_within_the_stated_ranges() {
        for r in 0..256 {
            for g in 0..256 {
                for b in (0..256).step_by(3).chain([255]) {
                    let (y, co, cg) = rgb_to_ycocg_r(r, g, b);
                    assert!((0..=255).contains(&y), "{r} {g} {b}");
                    assert!((-255..=255).contains(&co) && (-255..=255).contains(&cg));
                    assert_eq!(ycocg_r_to_rgb(y, co, cg), (r, g, b));
                }
            }
        }
    }

    #[test]
    fn grey_has_zero_chroma() {
        for v in [0, 1, 128, 255] {
            assert_eq!(rgb_to_ycocg_r(v, v, v), (v, 0, 0));
        }
    }
}

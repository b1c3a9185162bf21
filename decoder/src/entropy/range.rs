//! Binary adaptive range coder (LZMA-style carry handling, 16-bit probabilities).
//!
//! Termination is minimal: the encoder picks the value in its final interval with the
//! most trailing zero bytes and drops trailing zeros, because the decoder reads zeros
//! past the end of its input. The leading byte LZMA always writes as 0 is not written.

/// Probability precision in bits.
const PROB_BITS: u32 = 16;
/// Adaptation rate: each coded bit moves the probability by 1/2^RATE of the distance.
/// 6 since blob version 3 (korea, every mode: -0.2 to -0.3 % against 5; etopo5 even;
/// 7 is worse again).
pub const RATE: u32 = 6;
const TOP: u32 = 1 << 24;

/// Probability that the next bit is 0, in 1/65536 units (kept within 32..=65504).
pub type Prob = u16;

/// Neutral probability.
pub const HALF: Prob = 1 << (PROB_BITS - 1);

/// Moves probability `p` (of a 0) towards the coded `bit` at the adaptation [`RATE`].
#[inline(always)]
pub fn adapt(p: &mut Prob, bit: bool) {
    if bit {
        *p -= *p >> RATE;
    } else {
        *p += ((65536 - *p as u32) >> RATE) as u16;
    }
    *p = (*p).clamp(32, 65504);
}

/// Range encoder writing into a byte vector.
pub struct Encoder {
    low: u64,
    range: u32,
    cache: u8,
    cache_size: u64,
    first: bool,
    out: Vec<u8>,
}

impl Default for Encoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Encoder {
    /// A fresh encoder.
    pub fn new() -> Self {
        Encoder {
            low: 0,
            range: u32::MAX,
            cache: 0,
            cache_size: 1,
            first: true,
            out: Vec::new(),
        }
    }

    fn shift_low(&mut self) {
        if (self.low as u32) < 0xFF00_0000 || (self.low >> 32) != 0 {
            let carry = (self.low >> 32) as u8;
            let mut temp = self.cache;
            loop {
                if self.first {
                    // LZMA's leading byte is always zero (no carry can reach it): skip it.
                    self.first = false;
                } else {
                    self.out.push(temp.wrapping_add(carry));
                }
                temp = 0xFF;
                self.cache_size -= 1;
                if self.cache_size == 0 {
                    break;
                }
            }
            self.cache = (self.low >> 24) as u8;
        }
        self.cache_size += 1;
        self.low = (self.low & 0x00FF_FFFF) << 8;
    }

    /// Encodes one bit with an adaptive probability.
    #[inline(always)]
    pub fn bit(&mut self, p: &mut Prob, bit: bool) {
        let bound = (self.range >> PROB_BITS) * *p as u32;
        if bit {
            self.low += bound as u64;
            self.range -= bound;
        } else {
            self.range = bound;
        }
        adapt(p, bit);
        while self.range < TOP {
            self.range <<= 8;
            self.shift_low();
        }
    }

    /// Encodes the low `count` bits of `value` (most significant first) at probability 1/2.
    pub fn bypass(&mut self, value: u32, count: u32) {
        for k in (0..count).rev() {
            self.range >>= 1;
            if (value >> k) & 1 == 1 {
                self.low += self.range as u64;
            }
            while self.range < TOP {
                self.range <<= 8;
                self.shift_low();
            }
        }
    }

    /// Terminates the stream and returns the bytes.
    pub fn finish(mut self) -> Vec<u8> {
        // Pick the value in [low, low + range) with the most trailing zero bits.
        let hi = self.low + self.range as u64;
        for k in (0..=32).rev() {
            let mask = (1u64 << k) - 1;
            let x = (self.low + mask) & !mask;
            if x < hi {
                self.low = x;
                break;
            }
        }
        for _ in 0..5 {
            self.shift_low();
        }
        while self.out.last() == Some(&0) {
            self.out.pop();
        }
        self.out
    }
}

/// Range decoder over a byte slice (reads zeros past its end).
pub struct Decoder<'a> {
    code: u32,
    range: u32,
    data: &'a [u8],
    pos: usize,
}

impl<'a> Decoder<'a> {
    /// Starts decoding `data`.
    pub fn new(data: &'a [u8]) -> Self {
        let mut d = Decoder {
            code: 0,
            range: u32::MAX,
            data,
            pos: 0,
        };
        for _ in 0..4 {
            d.code = (d.code << 8) | d.next() as u32;
        }
        d
    }

    #[inline(always)]
    fn next(&mut self) -> u8 {
        let b = self.data.get(self.pos).copied().unwrap_or(0);
        self.pos += 1;
        b
    }

    /// Bytes consumed so far, counting the zeros read past the end.
    pub fn consumed(&self) -> usize {
        self.pos
    }

    /// Decodes one bit with an adaptive probability.
    #[inline(always)]
    pub fn bit(&mut self, p: &mut Prob) -> bool {
        let bound = (self.range >> PROB_BITS) * *p as u32;
        let bit = self.code >= bound;
        if bit {
            self.code -= bound;
            self.range -= bound;
        } else {
            self.range = bound;
        }
        adapt(p, bit);
        while self.range < TOP {
            self.range <<= 8;
            self.code = (self.code << 8) | self.next() as u32;
        }
        bit
    }

    /// Decodes `count` equiprobable bits, most significant first.
    pub fn bypass(&mut self, count: u32) -> u32 {
        let mut v = 0;
        for _ in 0..count {
            self.range >>= 1;
            let bit = self.code >= self.range;
            if bit {
                self.code -= self.range;
            }
            v = (v << 1) | bit as u32;
            while self.range < TOP {
                self.range <<= 8;
                self.code = (self.code << 8) | self.next() as u32;
            }
        }
        v
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;

    #[test]
    fn decoder_reproduces_encoded_bits_with_minimal_termination() {
        let mut seed = 1u64;
        for len in [0usize, 1, 2, 7, 100, 5000] {
            let bits: Vec<(bool, bool, u32)> = (0..len)
                .map(|_| {
                    seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
                    (
                        (seed >> 40).is_multiple_of(10),
                        (seed >> 20) & 1 == 1,
                        (seed >> 33) as u32 & 0x3FF,
                    )
                })
                .collect();
            let mut probs = [HALF; 3];
            let mut e = Encoder::new();
            for &(b, use_bypass, v) in &bits {
                e.bit(&mut probs[0], b);
                if use_bypass {
                    e.bypass(v, 10);
                }
                e.bit(&mut probs[1], !b);
            }
            let out = e.finish();
            let mut probs = [HALF; 3];
            let mut d = Decoder::new(&out);
            for &(b, use_bypass, v) in &bits {
                assert_eq!(d.bit(&mut probs[0]), b);
                if use_bypass {
                    assert_eq!(d.bypass(10), v);
                }
                assert_eq!(d.bit(&mut probs[1]), !b);
            }
        }
    }

    #[test]
    fn a_stream_of_likely_bits_costs_almost_nothing() {
        let mut p = HALF;
        let mut e = Encoder::new();
        for _ in 0..1000 {
            e.bit(&mut p, false);
        }
        assert!(e.finish().len() <= 3);
    }
}

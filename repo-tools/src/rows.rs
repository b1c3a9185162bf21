//! Planar repositories a band of rows at a time: the channels of an encoding decoded in
//! step (`build` measures out-of-core colour builds with it, `verify --stream` checks
//! repositories larger than memory), and the RGB error accumulated in pixel order.

use anyhow::{Result, anyhow};
use quincunx_codec::colour::ycocg_r_to_rgb;
use quincunx_codec::stream::{self, RowDecode};

/// Gives a diamond's blob of one channel: `(level, index) -> bytes` (`None`: no blob).
pub type BlobOf<'a> = dyn Fn(usize, usize) -> Result<Option<Vec<u8>>, stream::IoError> + Sync + 'a;

/// Receives row `r` of every channel, as decoded integers ([`StepChannel::units`] turns
/// them into units).
pub type OnRow<'a> = dyn FnMut(usize, &[Vec<i32>]) -> Result<()> + 'a;

/// One channel to decode: its encoding, where its blobs come from, and its units
/// (`value = offset + integer x scale`).
pub struct StepChannel<'a> {
    /// The encoding without its blobs.
    pub decode: RowDecode<'a>,
    /// Its blobs.
    pub blob: &'a BlobOf<'a>,
    /// Units per integer.
    pub scale: f64,
    /// Units at integer 0.
    pub offset: f64,
}

impl StepChannel<'_> {
    /// A row of decoded integers in units.
    pub fn units(&self, row: &[i32]) -> Vec<f64> {
        row.iter()
            .map(|&v| self.offset + v as f64 * self.scale)
            .collect()
    }
}

/// Decodes `channels` in step, each on its own thread, and hands every row of all of
/// them, as integers, to `on_row(row, channels' rows)` in order. Memory: a few diamond
/// heights of rows per octave and channel.
pub fn decode_in_step(
    channels: &[StepChannel<'_>],
    height: usize,
    on_row: &mut OnRow<'_>,
) -> Result<()> {
    std::thread::scope(|scope| {
        let mut receivers = Vec::new();
        let mut workers = Vec::new();
        for ch in channels {
            let (tx, rx) = std::sync::mpsc::sync_channel::<Vec<i32>>(16);
            receivers.push(rx);
            workers.push(scope.spawn(move || {
                stream::decode_rows(ch.decode, ch.blob, &mut |_, row| {
                    tx.send(row.to_vec()).map_err(Into::into)
                })
            }));
        }
        let mut result = Ok(());
        for r in 0..height {
            let rows: Result<Vec<Vec<i32>>, _> = receivers.iter().map(|rx| rx.recv()).collect();
            match rows {
                Ok(rows) => {
                    if let Err(e) = on_row(r, &rows) {
                        result = Err(e);
                        break;
                    }
                }
                Err(_) => {
                    result = Err(anyhow!("decoding stopped before row {r}"));
                    break;
                }
            }
        }
        // A worker blocked on a full channel stops once its receiver is gone.
        drop(receivers);
        for w in workers {
            match w.join() {
                Ok(Ok(())) => {}
                Ok(Err(e)) => return Err(anyhow!("decoding a channel: {e}")),
                Err(_) => return Err(anyhow!("a decoding thread panicked")),
            }
        }
        result
    })
}

/// RMS and largest RGB error of three decoded YCoCg-R channels against `image`: the
/// channels decoded in step, rounded as `encode::decode` and the in-memory measurement
/// round them, compared in pixel order. With `hash`, every row's integers also go into it.
pub fn rgb_error_in_step(
    channels: &[StepChannel<'_>],
    image: &crate::input::RgbImage,
    mut hash: Option<&mut crate::verify::ReconstructionHash>,
) -> Result<(f64, f64)> {
    if channels.len() != 3 {
        return Err(anyhow!("a colour repository needs 3 channels"));
    }
    let w = image.width;
    let mut error = RgbError::default();
    decode_in_step(channels, image.height, &mut |r, values| {
        if let Some(hash) = hash.as_deref_mut() {
            hash.add(values);
        }
        let ints: Vec<Vec<i32>> = values
            .iter()
            .zip(channels)
            .map(|(row, ch)| ch.units(row).iter().map(|v| v.round() as i32).collect())
            .collect();
        error.add(
            &image.pixels[r * w..(r + 1) * w],
            &ints[0],
            &ints[1],
            &ints[2],
        );
        Ok(())
    })?;
    Ok(error.finish())
}

/// RMS and largest absolute error over all RGB components of decoded YCoCg-R values
/// (clamped to 0..=255) against the source pixels, added up in pixel order.
#[derive(Debug, Default)]
pub struct RgbError {
    sum: f64,
    max: i32,
    pixels: usize,
}

impl RgbError {
    /// Adds pixels and their decoded `y`, `co`, `cg` (same order).
    pub fn add(&mut self, pixels: &[[u8; 3]], y: &[i32], co: &[i32], cg: &[i32]) {
        for (k, src) in pixels.iter().enumerate() {
            let (r, g, b) = ycocg_r_to_rgb(y[k], co[k], cg[k]);
            for (got, want) in [r, g, b].into_iter().zip(src) {
                let d = (got.clamp(0, 255) - *want as i32).abs();
                self.max = self.max.max(d);
                self.sum += (d * d) as f64;
            }
        }
        self.pixels += pixels.len();
    }

    /// `(rms, max)`.
    pub fn finish(&self) -> (f64, f64) {
        (
            (self.sum / (3 * self.pixels.max(1)) as f64).sqrt(),
            self.max as f64,
        )
    }
}

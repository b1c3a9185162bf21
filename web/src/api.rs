//! The module's calls on plain byte buffers, as the exports in `abi.rs` make them (and as
//! native tests make them): objects by handle, numbers little-endian, JSON where the page
//! wants objects.

use std::collections::HashMap;

use bytes::Bytes;
use glam::DVec3;

use quincunx_client_core::fetch::ranges::Step;
use quincunx_client_core::fetch::{FetchError, Key};
use quincunx_client_core::refine::Clock;
use quincunx_decoder::incremental::{PlanarRefiner, SphereRefiner};
use quincunx_meta::Domain as MetaDomain;

use crate::client::{Camera, Client, WebError, ms, view_of};
use crate::decode::AnswerDecoder;
use crate::open::Open;
use crate::pack::{FirstRead, PackReader, RangeAnswer};
use crate::wire::{Reader, Writer};

/// A client in its domain.
pub enum AnyClient {
    /// On a plane.
    Planar(Box<Client<PlanarRefiner>>),
    /// On a planet.
    Sphere(Box<Client<SphereRefiner>>),
}

/// Calls `$e` with `$c` bound to the client, whatever its domain.
macro_rules! with_client {
    ($client:expr, $c:ident => $e:expr) => {
        match $client {
            AnyClient::Planar($c) => $e,
            AnyClient::Sphere($c) => $e,
        }
    };
}

enum Object {
    Decoder(AnswerDecoder),
    Client(AnyClient),
    Pack(Box<PackReader>),
}

/// Every object the page holds, by handle.
#[derive(Default)]
pub struct Module {
    objects: HashMap<u32, Object>,
    next: u32,
}

fn parse_open(input: &[u8]) -> Result<Open, WebError> {
    serde_json::from_slice(input).map_err(|e| format!("opening: {e}"))
}

/// What an answer's `kind` byte says happened.
fn result_of(
    kind: u8,
    r: &mut Reader<'_>,
    rest: &[u8],
) -> Result<Result<(u16, Bytes), FetchError>, WebError> {
    let text = || String::from_utf8_lossy(rest).into_owned();
    Ok(match kind {
        0 => {
            let status = u16::try_from(r.u32().map_err(|e| e.to_string())?)
                .map_err(|_| "status out of range".to_string())?;
            let body = r
                .take(rest.len().saturating_sub(4))
                .map_err(|e| e.to_string())?;
            Ok((status, Bytes::copy_from_slice(body)))
        }
        1 => Err(FetchError::Connection(text())),
        2 => Err(FetchError::Timeout(ms(r
            .f64()
            .map_err(|e| e.to_string())?)?)),
        3 => Err(FetchError::Changed(text())),
        4 => Err(FetchError::Protocol(text())),
        k => return Err(format!("answer kind {k}")),
    })
}

impl Module {
    fn insert(&mut self, o: Object) -> u32 {
        self.next = self.next.wrapping_add(1).max(1);
        self.objects.insert(self.next, o);
        self.next
    }

    /// Drops object `h`.
    pub fn free(&mut self, h: u32) {
        self.objects.remove(&h);
    }

    fn client(&mut self, h: u32) -> Result<&mut AnyClient, WebError> {
        match self.objects.get_mut(&h) {
            Some(Object::Client(c)) => Ok(c),
            _ => Err(format!("no client {h}")),
        }
    }

    /// A decoder of the session the JSON [`Open`] describes.
    pub fn decoder_new(&mut self, input: &[u8]) -> Result<u32, WebError> {
        let d = AnswerDecoder::new(&parse_open(input)?)?;
        Ok(self.insert(Object::Decoder(d)))
    }

    /// Decodes an answer: input `u8 layer, u8 packaged, key, body`.
    pub fn decoder_decode(&mut self, h: u32, input: &[u8]) -> Result<Vec<u8>, WebError> {
        let Some(Object::Decoder(d)) = self.objects.get(&h) else {
            return Err(format!("no decoder {h}"));
        };
        let mut r = Reader::new(input);
        let (layer, packaged, key) = header(&mut r)?;
        d.decode(layer, key, &input[HEADER..], packaged != 0)
    }

    /// A client of the session the JSON [`Open`] describes.
    pub fn client_new(&mut self, input: &[u8], now_ms: f64) -> Result<u32, WebError> {
        let open = parse_open(input)?;
        let now = ms(now_ms)?;
        let c = match open.elevation.meta.domain {
            MetaDomain::Planar => AnyClient::Planar(Box::new(Client::new(&open, now)?)),
            MetaDomain::Sphere => AnyClient::Sphere(Box::new(Client::new(&open, now)?)),
        };
        Ok(self.insert(Object::Client(c)))
    }

    /// An answer: input `u8 layer, u8 kind, key`, then for kind 0 (HTTP) `u32 status,
    /// body`, 1 (connection failure) a message, 2 (timeout) `f64 ms`, 3 (the repository
    /// file changed) and 4 (a malformed answer) a message. Returns 0, or 1 / 2 when the
    /// body is to be decoded bare / as a package.
    pub fn client_answer(&mut self, h: u32, input: &[u8], now_ms: f64) -> Result<i32, WebError> {
        let now = ms(now_ms)?;
        let mut r = Reader::new(input);
        let (layer, kind, key) = header(&mut r)?;
        let result = result_of(kind, &mut r, &input[HEADER..])?;
        let decode = with_client!(self.client(h)?, c => c.answer(layer, key, result, now)?);
        Ok(match decode {
            None => 0,
            Some(false) => 1,
            Some(true) => 2,
        })
    }

    /// A decoded body: input `u8 layer, u8 0, key`, then the decoder's output.
    pub fn client_decoded(&mut self, h: u32, input: &[u8], now_ms: f64) -> Result<(), WebError> {
        let now = ms(now_ms)?;
        let mut r = Reader::new(input);
        let (layer, _, key) = header(&mut r)?;
        with_client!(self.client(h)?, c => c.decoded(layer, key, &input[HEADER..], now))
    }

    /// A body the decoder refused: input `u8 layer, u8 0, key`, then the reason (UTF-8).
    pub fn client_decode_failed(
        &mut self,
        h: u32,
        input: &[u8],
        now_ms: f64,
    ) -> Result<(), WebError> {
        let now = ms(now_ms)?;
        let mut r = Reader::new(input);
        let (layer, _, key) = header(&mut r)?;
        let reason = String::from_utf8_lossy(&input[HEADER..]).into_owned();
        with_client!(self.client(h)?, c => c.decode_failed(layer, key, reason, now))
    }

    /// One frame: input `f64 position[3], forward[3], up[3], fov_y_rad, tolerance_px,
    /// u32 viewport[2]`; `budget_ms` of refinement read from `clock`. Returns flags: 1
    /// full quality (nothing left to refine or fetch for the view), 2 settled (full
    /// quality, or the best cut the budgets allow), 4 converged (nothing left at all).
    pub fn client_frame(
        &mut self,
        h: u32,
        input: &[u8],
        now_ms: f64,
        budget_ms: f64,
        clock: &dyn Clock,
    ) -> Result<i32, WebError> {
        let now = ms(now_ms)?;
        let budget = ms(budget_ms)?;
        let mut r = Reader::new(input);
        let mut v3 = || -> Result<DVec3, WebError> {
            let mut a = [0.0; 3];
            for x in &mut a {
                *x = r.f64().map_err(|e| e.to_string())?;
            }
            Ok(DVec3::from_array(a))
        };
        let (position, forward, up) = (v3()?, v3()?, v3()?);
        let fov_y_rad = r.f64().map_err(|e| e.to_string())?;
        let tolerance = r.f64().map_err(|e| e.to_string())?;
        let viewport = [
            r.u32().map_err(|e| e.to_string())?,
            r.u32().map_err(|e| e.to_string())?,
        ];
        r.finish().map_err(|e| e.to_string())?;
        let camera = Camera {
            position,
            forward,
            up,
            fov_y_rad,
        };
        let view = view_of(camera, viewport, tolerance)?;
        let f = with_client!(self.client(h)?, c => c.frame(&view, now, budget, clock))?;
        let wanted = f.wanted == 0;
        Ok(i32::from(f.refine.full_quality && wanted)
            | i32::from(f.refine.settled() && wanted) << 1
            | i32::from(f.refine.converged) << 2)
    }

    /// The requests to send now: `u32 count, (u8 layer, u8 packaged, key)*`.
    pub fn client_plan(&mut self, h: u32, now_ms: f64) -> Result<Vec<u8>, WebError> {
        let now = ms(now_ms)?;
        let planned = with_client!(self.client(h)?, c => c.plan(now));
        let mut w = Writer::default();
        w.count(planned.len());
        for (layer, key, packaged) in planned {
            w.u8(layer);
            w.u8(u8::from(packaged));
            w.key(key);
        }
        Ok(w.out)
    }

    /// Milliseconds until the planners next act on their own (a retry), or -1.
    pub fn client_wake_in(&mut self, h: u32, now_ms: f64) -> Result<f64, WebError> {
        let now = ms(now_ms)?;
        let at = with_client!(self.client(h)?, c => c.wake_at(now));
        Ok(at.map_or(-1.0, |t| t.saturating_sub(now).as_secs_f64() * 1000.0))
    }

    /// The cut's changes ([`Client::cut_changes`]).
    pub fn client_changes(&mut self, h: u32) -> Result<Vec<u8>, WebError> {
        Ok(with_client!(self.client(h)?, c => c.cut_changes()))
    }

    /// The next changes report the whole cut.
    pub fn client_restart(&mut self, h: u32) -> Result<(), WebError> {
        with_client!(self.client(h)?, c => c.restart_cut_changes());
        Ok(())
    }

    /// Bounds the cut (`max < 0`: unbounded).
    pub fn client_set_max_cut_halves(&mut self, h: u32, max: f64) -> Result<(), WebError> {
        let max = (max >= 0.0).then(|| max.min(usize::MAX as f64) as usize);
        with_client!(self.client(h)?, c => c.set_max_cut_halves(max));
        Ok(())
    }

    /// JSON: the world frame and metric.
    pub fn client_info(&mut self, h: u32) -> Result<Vec<u8>, WebError> {
        Ok(with_client!(self.client(h)?, c => c.info())
            .to_string()
            .into_bytes())
    }

    /// JSON: the figures.
    pub fn client_stats(&mut self, h: u32) -> Result<Vec<u8>, WebError> {
        Ok(with_client!(self.client(h)?, c => c.stats())
            .to_string()
            .into_bytes())
    }

    /// JSON: the cut check.
    pub fn client_check(&mut self, h: u32) -> Result<Vec<u8>, WebError> {
        Ok(with_client!(self.client(h)?, c => c.check_cut())
            .to_string()
            .into_bytes())
    }

    /// `f64 lo, f64 hi`: the cut's height range, metres.
    pub fn client_height_range(&mut self, h: u32) -> Result<Vec<u8>, WebError> {
        let (lo, hi) = with_client!(self.client(h)?, c => c.height_range());
        let mut w = Writer::default();
        w.f64(lo);
        w.f64(hi);
        Ok(w.out)
    }
}

/// A string the page passes (`""`: none).
fn opt_str(v: &[u8]) -> Result<Option<&str>, WebError> {
    let s = std::str::from_utf8(v).map_err(|e| e.to_string())?;
    Ok((!s.is_empty()).then_some(s))
}

/// An answer as the page saw it: `u32 status, bytes content_range, bytes etag`, then the
/// body (the rest).
fn range_answer<'a>(r: &mut Reader<'a>, input: &'a [u8]) -> Result<RangeAnswer<'a>, WebError> {
    let e = |e: crate::wire::WireError| e.to_string();
    let status = u16::try_from(r.u32().map_err(e)?).map_err(|_| "status out of range")?;
    let content_range = opt_str(r.bytes().map_err(e)?)?;
    let etag = opt_str(r.bytes().map_err(e)?)?;
    let body = &input[r.position()..];
    Ok(RangeAnswer {
        status,
        content_range,
        etag,
        body,
    })
}

/// A range reader's step for the page: `u32 n, key*` (leaves); `u32 n, (key, u8 kind,
/// bytes payload)*` (answers to hand to [`Module::client_answer`] as they are: kind 0
/// `u32 200, blob` or another status, or a failure's kind and message); `u32 n, (f64
/// tag, f64 offset, f64 len)*` (range requests to send); `f64` bytes besides blobs.
fn write_step(step: Step) -> Vec<u8> {
    let mut w = Writer::default();
    w.count(step.leaves.len());
    for k in step.leaves {
        w.key(k);
    }
    w.count(step.blobs.len());
    for (k, result) in step.blobs {
        w.key(k);
        let mut payload = Writer::default();
        let kind = match result {
            Ok(blob) => {
                payload.u32(200);
                payload.out.extend_from_slice(&blob);
                0
            }
            Err(FetchError::Status(s)) => {
                payload.u32(u32::from(s));
                0
            }
            Err(FetchError::Connection(m)) => {
                payload.out.extend_from_slice(m.as_bytes());
                1
            }
            Err(FetchError::Timeout(t) | FetchError::Deadline(t)) => {
                payload.f64(t.as_secs_f64() * 1000.0);
                2
            }
            Err(FetchError::Changed(m)) => {
                payload.out.extend_from_slice(m.as_bytes());
                3
            }
            Err(e) => {
                payload.out.extend_from_slice(e.to_string().as_bytes());
                4
            }
        };
        w.u8(kind);
        w.bytes(&payload.out);
    }
    w.count(step.requests.len());
    for r in step.requests {
        w.f64(r.tag as f64);
        w.f64(r.range.offset as f64);
        w.f64(r.range.len as f64);
    }
    w.f64(step.overhead_bytes as f64);
    w.out
}

impl Module {
    fn pack(&mut self, h: u32) -> Result<&mut PackReader, WebError> {
        match self.objects.get_mut(&h) {
            Some(Object::Pack(p)) => Ok(p),
            _ => Err(format!("no repository file {h}")),
        }
    }

    /// The first read of a repository file: input `bytes url`, then the answer
    /// (`u32 status, bytes content_range, bytes etag, body`). Output `f64 file_len, f64
    /// open_len` ([`PackReader::first`]).
    pub fn pack_first(&mut self, input: &[u8]) -> Result<Vec<u8>, WebError> {
        let mut r = Reader::new(input);
        let url = std::str::from_utf8(r.bytes().map_err(|e| e.to_string())?)
            .map_err(|e| e.to_string())?;
        let answer = range_answer(&mut r, input)?;
        let first = PackReader::first(url, &answer)?;
        let mut w = Writer::default();
        w.f64(first.file_len as f64);
        w.f64(first.open_len as f64);
        Ok(w.out)
    }

    /// Opens a repository file: input `bytes url, f64 file_len, f64 open_len, bytes etag,
    /// bytes first_body, u8 has_rest`, then (if it has) the rest's answer. Returns its
    /// handle; output the JSON `{"meta": <metadata>, "etag": <the pinned ETag> | null,
    /// "fileLen"}`.
    pub fn pack_new(&mut self, input: &[u8]) -> Result<(u32, Vec<u8>), WebError> {
        let e = |e: crate::wire::WireError| e.to_string();
        let mut r = Reader::new(input);
        let url = std::str::from_utf8(r.bytes().map_err(e)?).map_err(|e| e.to_string())?;
        let [file_len, open_len] = [r.f64().map_err(e)?, r.f64().map_err(e)?].map(|v| {
            if v.is_finite() && v >= 0.0 {
                v as u64
            } else {
                u64::MAX
            }
        });
        let etag = opt_str(r.bytes().map_err(e)?)?;
        let first_body = r.bytes().map_err(e)?;
        let rest = match r.u8().map_err(e)? {
            0 => None,
            _ => Some(range_answer(&mut r, input)?),
        };
        let first = FirstRead { file_len, open_len };
        let (pack, meta) = PackReader::open(url, first, first_body, etag, rest.as_ref())?;
        let out = serde_json::json!({
            "meta": meta,
            "etag": pack.etag(),
            "fileLen": file_len,
        });
        let h = self.insert(Object::Pack(Box::new(pack)));
        Ok((h, out.to_string().into_bytes()))
    }

    /// What fetching keys takes: input `u32 n, (u8 packaged, key)*` (as
    /// [`Module::client_plan`] gives them, without the layer). Output: a step
    /// (`write_step`).
    pub fn pack_plan(&mut self, h: u32, input: &[u8]) -> Result<Vec<u8>, WebError> {
        let e = |e: crate::wire::WireError| e.to_string();
        let mut r = Reader::new(input);
        let n = r.count(25).map_err(e)?;
        let mut keys = Vec::with_capacity(n);
        for _ in 0..n {
            let packaged = r.u8().map_err(e)? != 0;
            keys.push((r.key().map_err(e)?, packaged));
        }
        r.finish().map_err(e)?;
        Ok(write_step(self.pack(h)?.plan(&keys)))
    }

    /// The answer to range request `tag`: input `f64 tag, u8 kind`, then for kind 0 the
    /// answer (`u32 status, bytes content_range, bytes etag, body`), 1 a failure's message
    /// (a network or CORS failure), 2 `f64 ms` (a timeout). Output: a step.
    pub fn pack_answered(&mut self, h: u32, input: &[u8]) -> Result<Vec<u8>, WebError> {
        let e = |e: crate::wire::WireError| e.to_string();
        let mut r = Reader::new(input);
        let tag = r.f64().map_err(e)?;
        if !(tag.is_finite() && tag >= 0.0) {
            return Err(format!("tag {tag}"));
        }
        let answer;
        let result = match r.u8().map_err(e)? {
            0 => {
                answer = range_answer(&mut r, input)?;
                Ok(&answer)
            }
            1 => Err(FetchError::Connection(
                String::from_utf8_lossy(&input[r.position()..]).into_owned(),
            )),
            2 => Err(FetchError::Timeout(ms(r.f64().map_err(e)?)?)),
            k => return Err(format!("answer kind {k}")),
        };
        Ok(write_step(self.pack(h)?.answered(tag as u64, result)))
    }
}

impl Module {
    /// A whole repository ([`crate::reconstruct::reconstruct_call`]) by the decoder of
    /// code `decoder` ([`crate::reconstruct::Decoder::from_code`]).
    pub fn reconstruct(
        &mut self,
        input: &[u8],
        decoder: u32,
        clock: &dyn Clock,
    ) -> Result<Vec<u8>, WebError> {
        let decoder = crate::reconstruct::Decoder::from_code(decoder)
            .ok_or_else(|| format!("unknown decoder {decoder}: 0 whole-raster, 1 refiners"))?;
        crate::reconstruct::reconstruct_call(input, decoder, clock)
    }
}

/// Bytes of the common header: `u8, u8, key`.
const HEADER: usize = 2 + 24;

fn header(r: &mut Reader<'_>) -> Result<(u8, u8, Key), WebError> {
    let e = |e: crate::wire::WireError| e.to_string();
    Ok((r.u8().map_err(e)?, r.u8().map_err(e)?, r.key().map_err(e)?))
}

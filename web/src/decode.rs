//! A decoding worker's side: the bytes of one answer (a blob, or a package carrying small
//! owned children's blobs) to decoded details in the [`crate::wire`] layout, with the
//! refiners, colour layer and packing the client has (the native network thread's
//! `Layer::spawn` decode, `Packing::unpack`, `ColourLayer::decode`).

use quincunx_client_core::fetch::Key;
use quincunx_client_core::fine::RenderDomain;
use quincunx_client_core::stream::{Packing, StreamCore};
use quincunx_decoder::incremental::{PlanarRefiner, Procedural, SphereRefiner};
use quincunx_meta::Domain as MetaDomain;

use crate::open::Open;
use crate::wire::{Wire, Writer};

/// The layers of one session, whose answers a worker decodes.
pub enum AnswerDecoder {
    /// A planar elevation repository (and colour).
    Planar(Box<StreamCore<PlanarRefiner>>),
    /// A planet.
    Sphere(Box<StreamCore<SphereRefiner>>),
}

/// The core of `open`'s repositories, in their domain.
pub(crate) fn core<R: RenderDomain>(open: &Open) -> Result<StreamCore<R>, String> {
    StreamCore::<R>::new(
        &open.elevation.name,
        &open.elevation.meta,
        open.colour.as_ref().map(|c| (c.name.as_str(), &c.meta)),
        open.config.stream()?,
        open.config.spacing_m,
        Procedural::Zero,
    )
    .map_err(|e| e.to_string())
}

impl AnswerDecoder {
    /// The decoder of the session `open` describes.
    pub fn new(open: &Open) -> Result<Self, String> {
        Ok(match open.elevation.meta.domain {
            MetaDomain::Planar => AnswerDecoder::Planar(Box::new(core(open)?)),
            MetaDomain::Sphere => AnswerDecoder::Sphere(Box::new(core(open)?)),
        })
    }

    /// Decodes the answer `bytes` to `key` of layer `layer` (0 elevation, 1 colour);
    /// `packaged`: it was asked for as a package. The value, then what it carried:
    /// `value, u32 count, (key, value)*`.
    pub fn decode(
        &self,
        layer: u8,
        key: Key,
        bytes: &[u8],
        packaged: bool,
    ) -> Result<Vec<u8>, String> {
        match self {
            AnswerDecoder::Planar(c) => decode_in(c, layer, key, bytes, packaged),
            AnswerDecoder::Sphere(c) => decode_in(c, layer, key, bytes, packaged),
        }
    }
}

fn decode_in<R: RenderDomain>(
    core: &StreamCore<R>,
    layer: u8,
    key: Key,
    bytes: &[u8],
    packaged: bool,
) -> Result<Vec<u8>, String> {
    match layer {
        0 => {
            let refiner = core.refiner();
            let decode =
                |k: Key, b: &[u8]| refiner.decode(R::id_of(k), b).map_err(|e| e.to_string());
            answer::<R, _, _>(core.elevation().packing(), key, bytes, packaged, &decode)
        }
        1 => {
            let (Some(layer), Some(state)) = (core.colour_layer(), core.colour()) else {
                return Err("no colour layer".into());
            };
            let decode = |k: Key, b: &[u8]| layer.decode(R::id_of(k), b);
            answer::<R, _, _>(state.packing(), key, bytes, packaged, &decode)
        }
        l => Err(format!("no layer {l}")),
    }
}

/// One answer: its value and what it carried, written out.
fn answer<R, T, D>(
    packing: Option<&Packing>,
    key: Key,
    bytes: &[u8],
    packaged: bool,
    decode: &D,
) -> Result<Vec<u8>, String>
where
    R: RenderDomain,
    T: Wire<R>,
    D: Fn(Key, &[u8]) -> Result<T, String>,
{
    let mut carried = Vec::new();
    let value = match packing.filter(|_| packaged) {
        Some(p) => p.unpack(key, bytes, decode, &mut carried)?,
        None => decode(key, bytes)?,
    };
    let mut w = Writer::default();
    value.write(&mut w);
    w.count(carried.len());
    for (k, v) in &carried {
        w.key(*k);
        v.write(&mut w);
    }
    Ok(w.out)
}

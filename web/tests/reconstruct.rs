//! `reconstruct_call`, by both of its decoders (whole-raster and refiners, which must
//! agree), against the codec's decoder: small repositories built in memory (planar,
//! planet, sparse planar and planet, colour) reconstruct exactly, and malformed input
//! (truncated tables, corrupt blobs, stray keys, huge rasters) is an error from both,
//! never a panic.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use quincunx_codec::diamond::{PlanarDomain, SphereDomain};
use quincunx_codec::encode::{
    Encoded, EncodedDomain, FromEncoded, RateMode, decode_integers, decode_sphere_integers, encode,
    encode_sphere,
};
use quincunx_codec::incremental::{PlanarRefiner, SphereRefiner};
use quincunx_meta::channels::frame_channels;
use quincunx_meta::{ChannelCoding, Domain, Metadata, Rate};
use quincunx_web::reconstruct::{Decoder, HEADER, reconstruct_call};

mod common;
use common::{Wall, geometry_of, metadata, options, planet, raster};

type Key = [i64; 3];

/// The centre of a storage key.
type Centre = Box<dyn Fn(&[u8]) -> Key>;

/// A way to damage a blob.
type Mutation = (&'static str, fn(&mut Vec<u8>));

/// The metadata record of channels `encs` (one geometry), as a build writes it.
fn metadata_of(encs: &[&Encoded]) -> Metadata {
    let e = encs[0];
    let (domain, m, levels, extent) = geometry_of(e);
    let colour = encs.len() == 3;
    let names = if colour {
        &["Y", "Co", "Cg"][..]
    } else {
        &["height"][..]
    };
    let channels = encs
        .iter()
        .zip(names)
        .map(|(e, name)| ChannelCoding {
            name: (*name).into(),
            value_scale: e.value_scale_m,
            value_offset: e.value_offset_m,
            steps: e.steps.clone(),
            model: e.model.to_bytes(),
            roots: e.roots.clone(),
            rate: Rate::Lossless,
        })
        .collect();
    metadata(
        domain,
        m,
        e.n,
        levels,
        extent,
        channels,
        e.coverage.as_ref().map(|c| c.to_bytes()),
        None,
    )
}

/// The stored blobs of channels `encs` by fetch key (colour: framed), sorted by key.
fn blobs(encs: &[&Encoded]) -> Vec<(Key, Vec<u8>)> {
    let e = encs[0];
    let centre: Centre = match e.domain {
        EncodedDomain::Planar { .. } => {
            let d: PlanarDomain = PlanarRefiner::from_encoded(e).unwrap().domain();
            Box::new(move |k| {
                let id = d.id_from_key(k).unwrap();
                [id.x, id.y, 0]
            })
        }
        EncodedDomain::Sphere { .. } => {
            let d: SphereDomain = SphereRefiner::from_encoded(e).unwrap().domain();
            Box::new(move |k| d.id_from_key(k).unwrap().c)
        }
    };
    let by_key: Vec<_> = encs.iter().map(|e| e.blobs_by_key().unwrap()).collect();
    let mut keys: Vec<&Vec<u8>> = by_key.iter().flat_map(|m| m.keys()).collect();
    keys.sort();
    keys.dedup();
    let mut out: Vec<(Key, Vec<u8>)> = keys
        .into_iter()
        .filter_map(|k| {
            let parts: Vec<Option<&[u8]>> =
                by_key.iter().map(|m| m.get(k).map(Vec::as_slice)).collect();
            Some((centre(k), frame_channels(&parts)?))
        })
        .collect();
    out.sort();
    out
}

/// The input of `reconstruct_call`.
fn input(meta: &Metadata, blobs: &[(Key, Vec<u8>)]) -> Vec<u8> {
    let json = serde_json::to_vec(meta).unwrap();
    let mut out = Vec::new();
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    out.extend_from_slice(&(blobs.len() as u32).to_le_bytes());
    for (key, bytes) in blobs {
        for v in key {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
        out.extend_from_slice(bytes);
    }
    out
}

/// The channels of `reconstruct_call`'s output.
fn channels(output: &[u8]) -> Vec<Vec<i32>> {
    let word = |k: usize| u32::from_le_bytes(output[k..k + 4].try_into().unwrap()) as usize;
    let (count, samples) = (word(0), word(4));
    let seconds = f64::from_le_bytes(output[8..16].try_into().unwrap());
    assert!(seconds.is_finite() && seconds >= 0.0, "{seconds}");
    assert_eq!(output.len(), HEADER + 4 * count * samples);
    output[HEADER..]
        .chunks_exact(4)
        .map(|b| i32::from_le_bytes(b.try_into().unwrap()))
        .collect::<Vec<_>>()
        .chunks(samples.max(1))
        .map(<[i32]>::to_vec)
        .take(count)
        .collect()
}

/// The codec's whole-raster decode of one channel.
fn whole(e: &Encoded) -> Vec<i32> {
    match e.domain {
        EncodedDomain::Planar { .. } => decode_integers(e).unwrap(),
        EncodedDomain::Sphere { .. } => decode_sphere_integers(e).unwrap(),
    }
}

/// Reconstructs `encs` through the module's call and compares with the codec.
fn reconstructs_exactly(encs: &[&Encoded]) -> Vec<u8> {
    let bytes = input(&metadata_of(encs), &blobs(encs));
    let out = reconstruct(&bytes).unwrap();
    let got = channels(&out);
    assert_eq!(got.len(), encs.len());
    for (c, e) in encs.iter().enumerate() {
        let want = whole(e);
        assert_eq!(got[c].len(), want.len(), "channel {c}: samples");
        let differ = got[c].iter().zip(&want).filter(|(a, b)| a != b).count();
        assert_eq!(
            differ, 0,
            "channel {c}: {differ} samples differ from the codec"
        );
    }
    bytes
}

fn korea_like(sparse: bool) -> Encoded {
    // Not a power of two plus one: border diamonds have masks.
    let hole = |x: usize, y: usize| sparse && (120..260).contains(&x) && (40..170).contains(&y);
    encode(
        &raster(300, 200, 0, hole),
        options(16, RateMode::RmsM(2.0), sparse),
    )
    .unwrap()
}

#[test]
fn planar_repository_reconstructs_as_the_codec_decodes() {
    let e = korea_like(false);
    reconstructs_exactly(&[&e]);
    let lossless = encode(
        &raster(97, 130, 3, |_, _| false),
        options(8, RateMode::Lossless, false),
    )
    .unwrap();
    reconstructs_exactly(&[&lossless]);
}

#[test]
fn sparse_planar_repository_with_holes_reconstructs_as_the_codec_decodes() {
    let e = korea_like(true);
    let coverage = e.coverage.as_ref().unwrap();
    assert!(coverage.covered_blocks() < coverage.blocks(), "no hole");
    reconstructs_exactly(&[&e]);
}

#[test]
fn planet_reconstructs_as_the_codec_decodes() {
    let e = encode_sphere(
        &planet(64, 16, 0.0, |_| false),
        options(16, RateMode::RmsM(3.0), false),
    )
    .unwrap();
    reconstructs_exactly(&[&e]);
}

#[test]
fn sparse_planet_reconstructs_as_the_codec_decodes() {
    // Data in a cap around a cube corner: it spans three faces and their edges.
    let centre = [0.6f64, 0.5, 0.62];
    let len = centre.iter().map(|c| c * c).sum::<f64>().sqrt();
    let far = move |q: [f64; 3]| {
        let cos = (0..3).map(|k| q[k] * centre[k] / len).sum::<f64>();
        cos < 40f64.to_radians().cos()
    };
    let e = encode_sphere(
        &planet(64, 8, 0.0, far),
        options(8, RateMode::Lossless, true),
    )
    .unwrap();
    assert!(e.coverage.is_some());
    reconstructs_exactly(&[&e]);
}

#[test]
fn colour_repository_reconstructs_three_channels() {
    let opts = options(16, RateMode::MaxErrorM(1.0), false);
    let encs: Vec<Encoded> = (1..=3)
        .map(|seed| encode(&raster(150, 111, seed, |_, _| false), opts).unwrap())
        .collect();
    let refs: Vec<&Encoded> = encs.iter().collect();
    reconstructs_exactly(&refs);
}

#[test]
fn every_truncation_of_the_input_is_an_error() {
    let e = encode(
        &raster(40, 33, 5, |_, _| false),
        options(8, RateMode::RmsM(2.0), false),
    )
    .unwrap();
    let bytes = input(&metadata_of(&[&e]), &blobs(&[&e]));
    for len in 0..bytes.len() {
        assert!(reconstruct(&bytes[..len]).is_err(), "cut at {len}");
    }
    let mut longer = bytes.clone();
    longer.push(0);
    assert!(reconstruct(&longer).is_err());
    reconstruct(&bytes).unwrap();
}

#[test]
fn corrupt_blobs_and_stray_keys_are_errors() {
    let e = korea_like(false);
    let meta = metadata_of(&[&e]);
    let good = blobs(&[&e]);
    // The largest blob: one with a payload.
    let big = (0..good.len()).max_by_key(|&k| good[k].1.len()).unwrap();
    let mutations: [Mutation; 4] = [
        ("flipped byte", |b| {
            let mid = b.len() / 2;
            b[mid] ^= 0x40;
        }),
        ("truncated", |b| {
            b.pop();
        }),
        ("header only", |b| b.truncate(3)),
        ("trailing byte", |b| b.push(7)),
    ];
    for (label, mutate) in mutations {
        let mut bad = good.clone();
        mutate(&mut bad[big].1);
        let err = reconstruct(&input(&meta, &bad)).unwrap_err();
        assert!(!err.is_empty(), "{label}");
    }
    // A key of no diamond, named in the error.
    for stray in [
        [3, 5, 0],
        [good[0].0[0], good[0].0[1], 1],
        [i64::MAX, i64::MIN, 0],
    ] {
        let mut bad = good.clone();
        bad.push((stray, vec![1, 2, 3]));
        let err = reconstruct(&input(&meta, &bad)).unwrap_err();
        let name = match stray {
            [x, y, 0] => format!("{x}/{y}"),
            [x, y, z] => format!("{x}/{y}/{z}"),
        };
        assert!(err.contains(&name), "{err}");
    }
    // A key given twice.
    let mut twice = good.clone();
    twice.push(good[0].clone());
    assert!(reconstruct(&input(&meta, &twice)).is_err());
    // An empty blob is a leaf's answer: no details there.
    let mut empty = good.clone();
    empty[big].1.clear();
    let _ = reconstruct(&input(&meta, &empty));
}

#[test]
fn bad_metadata_and_huge_rasters_are_errors() {
    assert!(reconstruct(&input_json(b"{", 0)).is_err());
    assert!(reconstruct(&input_json(b"null", 0)).is_err());
    let e = encode(
        &raster(40, 33, 5, |_, _| false),
        options(8, RateMode::RmsM(2.0), false),
    )
    .unwrap();
    let mut meta = metadata_of(&[&e]);
    meta.channels.clear();
    assert!(reconstruct(&input(&meta, &[])).is_err());
    // The largest raster the limits allow: refused before anything is allocated.
    let mut huge = metadata_of(&[&e]);
    huge.extent = [1 << 24, 1 << 24];
    huge.m = 24;
    huge.levels = 42;
    huge.channels[0].steps = vec![256; 42];
    let err = reconstruct(&input(&huge, &[])).unwrap_err();
    assert!(err.contains("memory"), "{err}");
    // At the value limit, but with the tables of 8 x 8 diamonds: refused by both decoders
    // before their memory is taken.
    let mut big = metadata_of(&[&e]);
    big.extent = [1 << 14, 1 << 14];
    big.m = 14;
    big.levels = 22;
    big.channels[0].steps = vec![256; 22];
    assert_eq!(big.n, 8);
    for decoder in [Decoder::Whole, Decoder::Refiners] {
        let clock = Wall(std::time::Instant::now());
        let Err(err) = reconstruct_call(&input(&big, &[]), decoder, &clock) else {
            panic!("{decoder:?}: a 2^28-sample raster of 8 x 8 diamonds was decoded");
        };
        assert!(err.contains("MiB of memory"), "{decoder:?}: {err}");
    }
    // A planet's metadata on planar blobs.
    let mut sphere = metadata_of(&[&e]);
    sphere.domain = Domain::Sphere;
    assert!(reconstruct(&input(&sphere, &blobs(&[&e]))).is_err());
}

/// `reconstruct_call` by both decoders, which must agree (the same output, or both an
/// error); the whole-raster decoder's answer.
fn reconstruct(bytes: &[u8]) -> Result<Vec<u8>, String> {
    let clock = Wall(std::time::Instant::now());
    let whole = reconstruct_call(bytes, Decoder::Whole, &clock);
    let refined = reconstruct_call(bytes, Decoder::Refiners, &clock);
    match (&whole, &refined) {
        // The same header and values; the seconds (bytes 8..16) differ.
        (Ok(a), Ok(b)) => assert!(
            a[..8] == b[..8] && a[HEADER..] == b[HEADER..],
            "the two decoders' outputs differ"
        ),
        (Err(_), Err(_)) => {}
        _ => panic!("the decoders disagree: whole-raster {whole:?}, refiners {refined:?}"),
    }
    whole
}

/// An input of raw metadata bytes and `count` (absent) blobs.
fn input_json(json: &[u8], count: u32) -> Vec<u8> {
    let mut out = (json.len() as u32).to_le_bytes().to_vec();
    out.extend_from_slice(json);
    out.extend_from_slice(&count.to_le_bytes());
    out
}

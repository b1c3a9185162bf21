//! Blob decoding of arbitrary bytes never panics.
//!
//! Input layout: byte 0 selects `N` (2^(1 + b % 9)) and the level group, byte 1 the
//! number of owned children (0..=4) and whether the checksum is patched to match, byte 2
//! the key length (0..=15), then the key, then the blob. With the checksum patched the
//! garbage reaches the entropy decoder instead of stopping at the CRC. The whole input is
//! also parsed as a `CodecModel`, and when that succeeds the blob is decoded with it too,
//! as is a valid model with every context explicit, its bytes taken from the blob bytes.

#![no_main]

use libfuzzer_sys::fuzz_target;
use quincunx_codec::blob::{self, BlobContext};
use quincunx_codec::entropy::{self, CodecModel};

fuzz_target!(|data: &[u8]| {
    let Some((&[sel, flags, key_len], rest)) = data.split_first_chunk::<3>() else {
        return;
    };
    let n = 1usize << (1 + sel % 9);
    let group = (sel as usize / 9) % entropy::GROUPS;
    let owned_children = (flags % 5) as usize;
    let patch_crc = flags & 0x80 != 0;
    let key_len = (key_len % 16) as usize;
    if rest.len() < key_len {
        return;
    }
    let (key, bytes) = rest.split_at(key_len);
    let ctx = BlobContext {
        key,
        n,
        group,
        mask: None,
        owned_children,
        step: if flags & 0x40 != 0 { 512 } else { 256 },
    };

    let mut blob_bytes = bytes.to_vec();
    if patch_crc && blob_bytes.len() >= blob::HEADER_BYTES {
        blob_bytes[0] = (blob::VERSION << 4) | n.trailing_zeros() as u8;
        let crc = blob::crc16(&[key, &blob_bytes[..1], &blob_bytes[blob::HEADER_BYTES..]]);
        blob_bytes[1..3].copy_from_slice(&crc.to_le_bytes());
    }
    if let Ok(content) = blob::decode(&blob_bytes, &ctx, &CodecModel::default()) {
        assert_eq!(content.q.len(), n * n);
        assert_eq!(content.child_classes.len(), owned_children);
    }

    // A model parsed from the input itself: accepted only when well formed (bitmap, then
    // one byte per set bit), and then it survives its own serialisation.
    if let Ok(model) = CodecModel::from_bytes(data) {
        assert_eq!(CodecModel::from_bytes(&model.to_bytes()).as_ref(), Ok(&model));
        let _ = blob::decode(&blob_bytes, &ctx, &model);
    }
    // And a model with every context explicit, its bytes taken from the input, so that
    // extreme trained priors meet garbage payloads.
    if !bytes.is_empty() {
        let map_len = entropy::CONTEXTS.div_ceil(8);
        let mut skewed = vec![0xFFu8; map_len];
        skewed[map_len - 1] = (0xFFu16 >> (map_len * 8 - entropy::CONTEXTS)) as u8;
        skewed.extend((0..entropy::CONTEXTS).map(|k| bytes[k % bytes.len()]));
        let model = CodecModel::from_bytes(&skewed).expect("every byte is a probability");
        let _ = blob::decode(&blob_bytes, &ctx, &model);
    }
});

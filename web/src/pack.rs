//! A repository file (`repository.pack`) read by the page with range requests, from any
//! static host that honours `Range` and allows the page's origin (CORS): the client
//! core's [`RangeReader`] decides what to ask for, the page only runs `fetch`, and every
//! answer's status, `Content-Range` and `ETag` are checked here by the native client's
//! code ([`PackIdentity::check_answer`]), so the browser refuses what it refuses.
//!
//! Opening: the page reads bytes `0..FIRST_READ` and hands the answer to
//! [`PackReader::first`], which says how many bytes opening needs; the page reads the
//! rest (if any) and calls [`PackReader::open`].
//!
//! The page sends **no `If-Match`**: in Chromium a page-set `If-Match` costs a CORS
//! preflight before every request and bypasses the HTTP cache (measured,
//! `web-demo/test/range-cors.test.mjs`). Every answer's `ETag` and file length are
//! compared with the first's instead, so a replaced file is still an error at its first
//! answer, never a mix of two builds. Then, for the keys a
//! client's planner releases, [`PackReader::plan`] gives range requests, and
//! [`PackReader::answered`] each answer's blobs, leaves and further requests
//! ([`Step`]).

use std::sync::Arc;

use bytes::Bytes;

use quincunx_client_core::fetch::range_answer::{self, PackIdentity};
use quincunx_client_core::fetch::ranges::{self, PackIndex, RangeConfig, RangeReader, Step};
use quincunx_client_core::fetch::{FetchError, Key};
use quincunx_meta::Metadata;
use quincunx_meta::pack::Section;

/// What the first read said.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FirstRead {
    /// The file's length.
    pub file_len: u64,
    /// Bytes from the start opening needs (at most `file_len`): more than were read,
    /// read the rest.
    pub open_len: u64,
}

/// An answer as the page's `fetch` saw it.
#[derive(Clone, Copy, Debug)]
pub struct RangeAnswer<'a> {
    /// The HTTP status.
    pub status: u16,
    /// The `Content-Range` header, if the page could read it.
    pub content_range: Option<&'a str>,
    /// The `ETag` header, if the page could read it.
    pub etag: Option<&'a str>,
    /// The body.
    pub body: &'a [u8],
}

impl RangeAnswer<'_> {
    fn content_range(&self) -> Result<Option<[u64; 3]>, String> {
        self.content_range
            .map(|v| {
                range_answer::parse_content_range(v.as_bytes())
                    .ok_or_else(|| format!("Content-Range {v:?} is not bytes first-last/total"))
            })
            .transpose()
    }
}

/// An opened repository file and the reader of its ranges.
#[derive(Debug)]
pub struct PackReader {
    identity: PackIdentity,
    reader: RangeReader,
}

impl PackReader {
    /// Bytes the page reads first.
    pub const FIRST_READ: u64 = ranges::FIRST_READ;

    /// The answer to the first read (`Range: bytes=0-(FIRST_READ - 1)`, no `If-Match`)
    /// of `url`: the file's length and how much opening needs, or why the file cannot
    /// be read this way (the server ignored `Range`, 403, 404, not a repository file).
    pub fn first(url: &str, answer: &RangeAnswer<'_>) -> Result<FirstRead, String> {
        let cr = answer.content_range()?;
        if answer.status == 206 && cr.is_none() {
            return Err(format!(
                "GET {url}: a 206 answer without a readable Content-Range (a cross-origin \
                 host must list Content-Range in Access-Control-Expose-Headers)"
            ));
        }
        let file_len = range_answer::opened_len(
            url,
            answer.status,
            cr,
            answer.body.len() as u64,
            Self::FIRST_READ,
        )?;
        let open_len = ranges::open_len(answer.body)
            .map_err(|e| format!("{url}: {e}"))?
            .min(file_len);
        Ok(FirstRead { file_len, open_len })
    }

    /// Opens `url` from the first read's answer (`first_body`, whose `ETag` was `etag`)
    /// and, if opening needs more, the answer to reading the rest (`rest`, asked from
    /// the first answer's end, checked like any later answer). Gives the reader and the
    /// repository's metadata.
    pub fn open(
        url: &str,
        first: FirstRead,
        first_body: &[u8],
        etag: Option<&str>,
        rest: Option<&RangeAnswer<'_>>,
    ) -> Result<(PackReader, Metadata), String> {
        let identity = PackIdentity {
            path: url.to_string(),
            file_len: first.file_len,
            etag: etag.map(str::to_string),
        };
        let mut front = first_body.to_vec();
        if first.open_len > front.len() as u64 {
            let rest =
                rest.ok_or_else(|| format!("{url}: opening needs bytes up to {}", first.open_len))?;
            let range = Section {
                offset: front.len() as u64,
                len: first.open_len - front.len() as u64,
            };
            let body = identity
                .check_answer(
                    range,
                    rest.status,
                    Bytes::copy_from_slice(rest.body),
                    rest.content_range()?,
                    rest.etag,
                )
                .map_err(|e| format!("opening {url}: {e}"))?;
            if body.len() as u64 != range.len {
                return Err(format!(
                    "opening {url}: {} bytes for a range of {}",
                    body.len(),
                    range.len
                ));
            }
            front.extend_from_slice(&body);
        }
        let (index, meta) =
            PackIndex::open(&front, first.file_len).map_err(|e| format!("{url}: {e}"))?;
        let reader = RangeReader::new(Arc::new(index), RangeConfig::default());
        Ok((PackReader { identity, reader }, meta))
    }

    /// The `ETag` every answer must carry (if the first had one).
    pub fn etag(&self) -> Option<&str> {
        self.identity.etag.as_deref()
    }

    /// What fetching `keys` takes; each key with whether the planner asked for its
    /// package (then its answer is the package, as a server's `/p/` URL answers it).
    pub fn plan(&mut self, keys: &[(Key, bool)]) -> Step {
        self.reader.plan(keys)
    }

    /// The answer to request `tag`: checked against the file opened, then read.
    pub fn answered(&mut self, tag: u64, answer: Result<&RangeAnswer<'_>, FetchError>) -> Step {
        let Some(range) = self.reader.range_of(tag) else {
            return Step::default();
        };
        let body = answer.and_then(|a| {
            let cr = a.content_range().map_err(FetchError::Protocol)?;
            self.identity
                .check_answer(range, a.status, Bytes::copy_from_slice(a.body), cr, a.etag)
        });
        self.reader.answered(tag, body)
    }

    /// The range request `tag` asks for, while it is pending.
    pub fn range_of(&self, tag: u64) -> Option<Section> {
        self.reader.range_of(tag)
    }

    /// Leaf directories loaded so far.
    pub fn loaded_tiles(&self) -> usize {
        self.reader.loaded_tiles()
    }
}

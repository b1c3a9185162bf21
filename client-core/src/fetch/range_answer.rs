//! What a range answer means, for any HTTP stack (the native client's, the browser's
//! `fetch`): the headers to send with a request of a repository file, and the checks of
//! its answer (status, `Content-Range`, `ETag`) before [`super::ranges::RangeReader`]
//! sees its bytes. One copy, so the browser refuses exactly what the native client does.

use bytes::Bytes;
use quincunx_meta::pack::Section;

use super::FetchError;

/// The identity of an opened repository file: every answer must be of this file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PackIdentity {
    /// Its path or URL, for messages.
    pub path: String,
    /// Its length (the first answer's `Content-Range` total).
    pub file_len: u64,
    /// Its `ETag` when opened: sent as `If-Match` (if strong) and compared with every
    /// answer's, so a replaced file is an error, never a mix of two builds.
    pub etag: Option<String>,
}

/// Whether an `ETag` is strong: `If-Match` compares strongly, so a weak one (`W/"..."`,
/// as some CDNs give) would never match; it is still compared with every answer's.
pub fn is_strong(etag: &str) -> bool {
    !etag.starts_with("W/")
}

/// A `Content-Range` value, `bytes first-last/total`: `[first, last, total]`, with
/// `total` `u64::MAX` for `*`, and `[u64::MAX, 0, total]` for `bytes */total` (a 416's).
pub fn parse_content_range(v: &[u8]) -> Option<[u64; 3]> {
    let rest = v.trim_ascii().strip_prefix(b"bytes ")?;
    let slash = rest.iter().position(|&b| b == b'/')?;
    let (span, total) = (&rest[..slash], &rest[slash + 1..]);
    if span == b"*" {
        return Some([u64::MAX, 0, parse_length(total)?]);
    }
    let dash = span.iter().position(|&b| b == b'-')?;
    let first = parse_length(&span[..dash])?;
    let last = parse_length(&span[dash + 1..])?;
    let total = if total == b"*" {
        u64::MAX
    } else {
        parse_length(total)?
    };
    (first <= last && last < total).then_some([first, last, total])
}

/// A decimal length (`Content-Length`, a `Content-Range` part): digits only, fitting a
/// `u64`.
pub fn parse_length(v: &[u8]) -> Option<u64> {
    let v = v.trim_ascii();
    if v.is_empty() {
        return None;
    }
    v.iter().try_fold(0u64, |acc, &d| {
        if d.is_ascii_digit() {
            acc.checked_mul(10)?.checked_add(u64::from(d - b'0'))
        } else {
            None
        }
    })
}

impl PackIdentity {
    /// The `If-Match` value to send: the pinned `ETag`, if strong.
    pub fn if_match(&self) -> Option<&str> {
        self.etag.as_deref().filter(|e| is_strong(e))
    }

    /// Checks an answer to a request for `range` against the file opened, and gives its
    /// body: `206` with exactly that `Content-Range` and the file's length and `ETag`
    /// (or a `200` of the whole file, if that was asked); anything else is an error that
    /// names what is wrong (`FetchError::Changed` when the file is another one now).
    pub fn check_answer(
        &self,
        range: Section,
        status: u16,
        body: Bytes,
        content_range: Option<[u64; 3]>,
        etag: Option<&str>,
    ) -> Result<Bytes, FetchError> {
        let total = self.file_len;
        let want = [range.offset, range.end().saturating_sub(1), total];
        match status {
            206 => {}
            200 if range.offset == 0 && range.len == total && body.len() as u64 == total => {
                return Ok(body);
            }
            200 => {
                return Err(FetchError::Protocol(format!(
                    "{}: the server ignored the Range header (200 with {} bytes)",
                    self.path,
                    body.len()
                )));
            }
            412 => return Err(self.changed("412 Precondition Failed: its ETag no longer matches")),
            416 => return Err(self.changed("416 Range Not Satisfiable: it is shorter now")),
            s => return Err(FetchError::Status(s)),
        }
        if let (Some(pinned), Some(now)) = (&self.etag, etag)
            && pinned != now
        {
            return Err(self.changed(&format!("its ETag was {pinned}, now {now}")));
        }
        match content_range {
            Some([.., t]) if t != total && t != u64::MAX => {
                Err(self.changed(&format!("it had {total} bytes, now {t}")))
            }
            Some([a, b, _]) if [a, b] == [want[0], want[1]] => Ok(body),
            other => Err(FetchError::Protocol(format!(
                "{}: asked for bytes {}-{}, the answer says {:?}",
                self.path, want[0], want[1], other
            ))),
        }
    }

    fn changed(&self, why: &str) -> FetchError {
        FetchError::Changed(format!(
            "{} changed since it was opened ({why}); open it again",
            self.path
        ))
    }
}

/// The file's length from the answer to the first read (`0-(first_read - 1)`), or why it
/// cannot be read with ranges: a `206` gives the `Content-Range` total; a `200` is the
/// whole file only if shorter than the first read (else the server ignored `Range`).
pub fn opened_len(
    url: &str,
    status: u16,
    content_range: Option<[u64; 3]>,
    body_len: u64,
    first_read: u64,
) -> Result<u64, String> {
    match (status, content_range) {
        (206, Some([0, _, total])) if total != u64::MAX => Ok(total),
        (200, _) if body_len < first_read => Ok(body_len),
        (200, _) => Err(format!(
            "GET {url}: the server ignored the Range header (200 with {body_len} bytes): \
             range requests are needed to read a repository file"
        )),
        (206, other) => Err(format!(
            "GET {url}: a 206 answer with Content-Range {other:?}"
        )),
        (status, _) => Err(format!("GET {url}: status {status}")),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn file(etag: Option<&str>) -> PackIdentity {
        PackIdentity {
            path: "/r.pack".into(),
            file_len: 1000,
            etag: etag.map(Into::into),
        }
    }

    const R: Section = Section {
        offset: 100,
        len: 10,
    };

    #[test]
    fn content_ranges_parse_and_refuse_nonsense() {
        assert_eq!(parse_content_range(b"bytes 0-9/100"), Some([0, 9, 100]));
        assert_eq!(parse_content_range(b" bytes 5-5/*"), Some([5, 5, u64::MAX]));
        assert_eq!(
            parse_content_range(b"bytes */100"),
            Some([u64::MAX, 0, 100])
        );
        for bad in [
            &b"bytes 9-0/100"[..],
            b"bytes 0-100/100",
            b"items 0-9/100",
            b"bytes 0-9",
            b"bytes -1-9/100",
            b"bytes 0-99999999999999999999/1",
        ] {
            assert_eq!(parse_content_range(bad), None, "{bad:?}");
        }
    }

    #[test]
    fn answers_of_another_file_or_range_are_refused_by_name() {
        let f = file(Some("\"a\""));
        let body = Bytes::from(vec![0; 10]);
        let ok = |cr, etag| f.check_answer(R, 206, body.clone(), cr, etag);
        assert!(ok(Some([100, 109, 1000]), Some("\"a\"")).is_ok());
        assert!(ok(Some([100, 109, u64::MAX]), None).is_ok());
        let changed = |r: Result<Bytes, FetchError>| matches!(r, Err(FetchError::Changed(_)));
        assert!(changed(ok(Some([100, 109, 1000]), Some("\"b\""))));
        assert!(changed(ok(Some([100, 109, 999]), Some("\"a\""))));
        assert!(changed(f.check_answer(R, 412, Bytes::new(), None, None)));
        assert!(changed(f.check_answer(R, 416, Bytes::new(), None, None)));
        assert!(matches!(
            ok(Some([0, 9, 1000]), Some("\"a\"")),
            Err(FetchError::Protocol(_))
        ));
        assert!(matches!(ok(None, None), Err(FetchError::Protocol(_))));
        let ignored = f.check_answer(R, 200, Bytes::from(vec![0; 1000]), None, None);
        assert!(
            format!("{}", ignored.unwrap_err()).contains("ignored the Range header"),
            "200"
        );
        assert_eq!(
            f.check_answer(R, 403, Bytes::new(), None, None),
            Err(FetchError::Status(403))
        );
        let whole = Section {
            offset: 0,
            len: 1000,
        };
        assert!(
            f.check_answer(whole, 200, Bytes::from(vec![0; 1000]), None, None)
                .is_ok()
        );
    }

    #[test]
    fn only_strong_etags_are_sent_as_if_match() {
        assert_eq!(file(Some("\"a\"")).if_match(), Some("\"a\""));
        assert_eq!(file(Some("W/\"a\"")).if_match(), None);
        assert_eq!(file(None).if_match(), None);
    }

    #[test]
    fn the_first_read_gives_the_length_or_says_why_not() {
        assert_eq!(
            opened_len("u", 206, Some([0, 16383, 50000]), 16384, 16384),
            Ok(50000)
        );
        assert_eq!(opened_len("u", 200, None, 900, 16384), Ok(900));
        assert!(
            opened_len("u", 200, None, 16384, 16384)
                .unwrap_err()
                .contains("ignored the Range header")
        );
        assert!(
            opened_len("u", 404, None, 0, 16384)
                .unwrap_err()
                .contains("status 404")
        );
        assert!(opened_len("u", 206, None, 10, 16384).is_err());
    }
}

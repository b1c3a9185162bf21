//! Packages served from a repository: a diamond's blob with its small owned children's
//! answers, assembled from the pack without decoding anything. The framing, the id
//! relations and the parser are [`quincunx_meta::answer`], which this re-exports.

pub use quincunx_meta::answer::*;

use crate::{Repository, Result, StoreError};

impl Repository {
    /// The package of the diamond centred at `c` (see the module docs): `None` when it
    /// has no blob (a leaf, or a level beyond the repository's), else its blob with the
    /// answers of its owned children that fit the inlining limit. A repository without
    /// a limit carries no children.
    pub fn package(&self, domain: &IdSpace, c: [i64; 3]) -> Result<Option<Vec<u8>>> {
        let limit = self.metadata().inline_max_bytes.unwrap_or(0) as usize;
        self.package_within(domain, c, usize::MAX, limit)
    }

    /// The package of `c`, or `None` when `c` has no blob or its package would exceed
    /// `cap` bytes (found out without reading more than about `cap` bytes of blobs).
    fn package_within(
        &self,
        domain: &IdSpace,
        c: [i64; 3],
        cap: usize,
        limit: usize,
    ) -> Result<Option<Vec<u8>>> {
        let (key, level) = domain.key_level(c).map_err(|r| self.bad(r))?;
        let levels = self.metadata().levels;
        if level >= levels {
            return Ok(None);
        }
        let Some(blob) = self.get(&key)? else {
            return Ok(None);
        };
        let mut size = 1 + varint_len(blob.len()) + blob.len();
        if size > cap {
            return Ok(None);
        }
        let mut children = Vec::new();
        if level + 1 < levels {
            let owned = domain.owned_children(c).map_err(|r| self.bad(r))?;
            for (i, k) in owned.into_iter().enumerate() {
                if let Some(answer) = self.package_within(domain, k, limit, limit)? {
                    size += varint_len(answer.len()) + answer.len();
                    if size > cap {
                        return Ok(None);
                    }
                    children.push((i, answer));
                }
            }
        }
        Ok(Some(write(&blob, &children, true)))
    }

    fn bad(&self, reason: String) -> StoreError {
        StoreError::BadMetadata {
            path: self.path().to_path_buf(),
            reason,
        }
    }
}

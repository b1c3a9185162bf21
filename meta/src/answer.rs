//! Packages: a diamond's blob with its small owned children's (spec:
//! `docs/blob-format.md`, "Packages").
//!
//! At 0.2-0.3 bits/sample the finest levels' blobs are a few tens of bytes, while an
//! HTTP/1.1 answer head is over 200. A repository built with an inlining limit `T`
//! ([`Metadata::inline_max_bytes`]) can therefore answer a diamond with a *package*: its
//! own blob, then the packages of those of its *owned* children (the children whose
//! first parent it is) that have a blob and whose package is at most `T` bytes. Every
//! diamond is owned by exactly one parent, so a carried blob arrives once, in the same
//! round trip as its owner's. A client asks for a package (`.../p/<centre>`) when it
//! expects to refine the diamond's children soon, and for the bare blob (`.../d/`)
//! otherwise; it asks for a child on its own when its owner's package did not carry it.
//! Leaves are not listed: the owner's blob already flags its owned children without
//! data.
//!
//! Layout of a package: byte `0xF0 | mask` (bit `i` set: the `i`-th owned child, in
//! child order, is carried), the own blob's length as a LEB128 varint, the own blob,
//! then for each set bit in order the child's length (varint) and the child's package.
//!
//! This is framing only: nothing here decodes a blob, so the server (which must never
//! decode) can assemble packages (`quincunx_store::Repository::package`), and the client
//! can split them without the store.

use quincunx_diamond::{PlanarDomain, PlanarId, SphereDomain, SphereId};

use crate::{Domain, Metadata};

/// The first byte's high nibble of a package (a check: the level says what to expect).
const PACKAGE_TAG: u8 = 0xF0;

/// A repository's id space with the few relations answers need, over centres `[x, y, z]`
/// (planar ids use `z = 0`).
#[derive(Clone, Copy, Debug)]
pub enum IdSpace {
    /// Planar square `[0, 2^m]^2`.
    Planar(PlanarDomain),
    /// Cube-mapped sphere `[-2^m, 2^m]^3`.
    Sphere(SphereDomain),
}

impl IdSpace {
    /// The id space of a repository's metadata.
    pub fn of(meta: &Metadata) -> std::result::Result<IdSpace, String> {
        let space = match meta.domain {
            Domain::Planar => {
                IdSpace::Planar(PlanarDomain::new(meta.m).map_err(|e| e.to_string())?)
            }
            Domain::Sphere => {
                IdSpace::Sphere(SphereDomain::new(meta.m).map_err(|e| e.to_string())?)
            }
        };
        Ok(space)
    }

    /// Coordinates in an id (2 planar, 3 sphere).
    pub fn dims(&self) -> usize {
        match self {
            IdSpace::Planar(_) => 2,
            IdSpace::Sphere(_) => 3,
        }
    }

    /// The storage key and level of a centre, or why it is not a diamond of this domain.
    pub fn key_level(&self, c: [i64; 3]) -> std::result::Result<(Vec<u8>, u32), String> {
        let r = match self {
            IdSpace::Planar(d) => {
                let id = planar(c);
                d.key(id).and_then(|k| Ok((k, d.level(id)?)))
            }
            IdSpace::Sphere(d) => {
                let id = SphereId { c };
                d.key(id).and_then(|k| Ok((k, d.level(id)?)))
            }
        };
        r.map_err(|e| e.to_string())
    }

    /// The centre of a storage key (the inverse of [`IdSpace::key_level`]).
    pub fn centre(&self, key: &[u8]) -> std::result::Result<[i64; 3], String> {
        let r = match self {
            IdSpace::Planar(d) => d.id_from_key(key).map(|id| [id.x, id.y, 0]),
            IdSpace::Sphere(d) => d.id_from_key(key).map(|id| id.c),
        };
        r.map_err(|e| e.to_string())
    }

    /// The level of a centre.
    pub fn level(&self, c: [i64; 3]) -> std::result::Result<u32, String> {
        let r = match self {
            IdSpace::Planar(d) => d.level(planar(c)),
            IdSpace::Sphere(d) => d.level(SphereId { c }),
        };
        r.map_err(|e| e.to_string())
    }

    /// The first parent (the owner) of a centre; `None` for roots.
    pub fn owner(&self, c: [i64; 3]) -> std::result::Result<Option<[i64; 3]>, String> {
        let r = match self {
            IdSpace::Planar(d) => d
                .parents(planar(c))
                .map(|p| p.first().map(|p| [p.x, p.y, 0])),
            IdSpace::Sphere(d) => d.parents(SphereId { c }).map(|p| p.first().map(|p| p.c)),
        };
        r.map_err(|e| e.to_string())
    }

    /// The children whose first parent is `c`, in child (side) order.
    pub fn owned_children(&self, c: [i64; 3]) -> std::result::Result<Vec<[i64; 3]>, String> {
        let children: Vec<[i64; 3]> = match self {
            IdSpace::Planar(d) => d
                .children(planar(c))
                .map_err(|e| e.to_string())?
                .into_iter()
                .map(|k| [k.x, k.y, 0])
                .collect(),
            IdSpace::Sphere(d) => d
                .children(SphereId { c })
                .map_err(|e| e.to_string())?
                .into_iter()
                .map(|k| k.c)
                .collect(),
        };
        let mut owned = Vec::with_capacity(children.len());
        for k in children {
            if self.owner(k)? == Some(c) {
                owned.push(k);
            }
        }
        Ok(owned)
    }
}

fn planar(c: [i64; 3]) -> PlanarId {
    PlanarId { x: c[0], y: c[1] }
}

/// A parsed answer: the diamond's own blob and the answers of the owned children carried
/// (by index among the owned children).
#[derive(Debug, PartialEq, Eq)]
pub struct Answer<'a> {
    /// The diamond's blob.
    pub blob: &'a [u8],
    /// `(owned child index, that child's answer)`, in index order.
    pub children: Vec<(usize, &'a [u8])>,
}

/// Why an answer could not be parsed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum AnswerError {
    /// A length or the mask runs past the end.
    #[error("answer truncated")]
    Truncated,
    /// A varint longer than 5 bytes or above `u32`.
    #[error("bad length field")]
    BadLength,
    /// Bytes left after the last child.
    #[error("{0} trailing bytes after the last child")]
    Trailing(usize),
    /// A package with an empty mask or an empty part.
    #[error("malformed package: {0}")]
    Malformed(&'static str),
}

/// Splits an answer: a package when `packaged` (it was asked for as one), else the bare
/// blob. Never panics and never allocates from an
/// untrusted length (at most 4 children are listed).
pub fn parse(bytes: &[u8], packaged: bool) -> std::result::Result<Answer<'_>, AnswerError> {
    let Some(&first) = bytes.first() else {
        return Err(AnswerError::Malformed("empty"));
    };
    if !packaged {
        return Ok(Answer {
            blob: bytes,
            children: Vec::new(),
        });
    }
    if first & 0xF0 != PACKAGE_TAG {
        return Err(AnswerError::Malformed("not a package"));
    }
    let mask = first & 0x0F;
    let mut at = 1;
    let part = |at: &mut usize| -> std::result::Result<&[u8], AnswerError> {
        let len = read_varint(bytes, at)? as usize;
        let end = at.checked_add(len).ok_or(AnswerError::Truncated)?;
        let part = bytes.get(*at..end).ok_or(AnswerError::Truncated)?;
        if part.is_empty() {
            return Err(AnswerError::Malformed("empty part"));
        }
        *at = end;
        Ok(part)
    };
    let blob = part(&mut at)?;
    let mut children = Vec::with_capacity(mask.count_ones() as usize);
    for i in 0..4 {
        if mask & (1 << i) != 0 {
            children.push((i, part(&mut at)?));
        }
    }
    if at != bytes.len() {
        return Err(AnswerError::Trailing(bytes.len() - at));
    }
    Ok(Answer { blob, children })
}

/// Writes an answer: a package when `packaged`, else the bare blob (`children` must then
/// be empty).
pub fn write(blob: &[u8], children: &[(usize, Vec<u8>)], packaged: bool) -> Vec<u8> {
    if !packaged {
        debug_assert!(children.is_empty());
        return blob.to_vec();
    }
    let mask = children.iter().fold(0u8, |m, (i, _)| m | (1 << i));
    let mut out = Vec::with_capacity(blob.len() + 6 * (children.len() + 1));
    out.push(PACKAGE_TAG | mask);
    write_varint(&mut out, blob.len());
    out.extend_from_slice(blob);
    let mut sorted: Vec<&(usize, Vec<u8>)> = children.iter().collect();
    sorted.sort_by_key(|(i, _)| *i);
    for (_, child) in sorted {
        write_varint(&mut out, child.len());
        out.extend_from_slice(child);
    }
    out
}

/// Appends `v` as a LEB128 varint (the lengths of packages and channel frames).
pub(crate) fn write_varint(out: &mut Vec<u8>, mut v: usize) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn read_varint(bytes: &[u8], at: &mut usize) -> std::result::Result<u32, AnswerError> {
    let mut v: u64 = 0;
    for shift in (0..35).step_by(7) {
        let b = *bytes.get(*at).ok_or(AnswerError::Truncated)?;
        *at += 1;
        v |= u64::from(b & 0x7F) << shift;
        if b & 0x80 == 0 {
            return u32::try_from(v).map_err(|_| AnswerError::BadLength);
        }
    }
    Err(AnswerError::BadLength)
}

/// Bytes of `v` as a LEB128 varint.
pub fn varint_len(v: usize) -> usize {
    let bits = usize::BITS - v.leading_zeros();
    (bits.max(1) as usize).div_ceil(7)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn answers_round_trip() {
        let blob = vec![0xF5, 1, 2, 3];
        assert_eq!(write(&blob, &[], false), blob);
        assert_eq!(parse(&blob, false).unwrap().blob, &blob[..]);
        let grand = write(&[0x25, 9], &[], true);
        assert_eq!(grand, vec![0xF0, 2, 0x25, 9]);
        let child = write(&[0x25, 7, 7], &[(1, grand.clone())], true);
        let big = write(&[0x25; 300], &[], true);
        let answer = write(&blob, &[(2, big.clone()), (0, child.clone())], true);
        assert_eq!(answer[0], 0xF5);
        let parsed = parse(&answer, true).unwrap();
        assert_eq!(parsed.blob, &blob[..]);
        assert_eq!(parsed.children, vec![(0, &child[..]), (2, &big[..])]);
        let inner = parse(parsed.children[0].1, true).unwrap();
        assert_eq!(inner.blob, &[0x25, 7, 7]);
        assert_eq!(inner.children, vec![(1, &grand[..])]);
        assert_eq!(parse(&grand, true).unwrap().children, vec![]);
    }

    #[test]
    fn malformed_answers_are_errors() {
        let good = write(&[0x25, 1], &[(0, write(&[0x25, 2], &[], true))], true);
        assert_eq!(parse(&[], true), Err(AnswerError::Malformed("empty")));
        assert_eq!(parse(&[], false), Err(AnswerError::Malformed("empty")));
        assert_eq!(
            parse(&[0x25, 1], true),
            Err(AnswerError::Malformed("not a package"))
        );
        assert!(parse(&[0xF0, 1], true).is_err());
        for cut in 1..good.len() {
            assert!(parse(&good[..cut], true).is_err(), "cut at {cut}");
        }
        let mut trailing = good.clone();
        trailing.push(0);
        assert_eq!(parse(&trailing, true), Err(AnswerError::Trailing(1)));
        assert_eq!(
            parse(&[0xF1, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0x01], true),
            Err(AnswerError::BadLength)
        );
        assert_eq!(
            parse(&[0xF1, 0xFF, 0xFF, 0xFF, 0xFF, 0x7F], true),
            Err(AnswerError::BadLength)
        );
        assert_eq!(
            parse(&[0xF1, 0, 1, 0x25], true),
            Err(AnswerError::Malformed("empty part"))
        );
        // Arbitrary bytes never panic.
        let mut x = 0x1234_5678u32;
        for len in 0..64 {
            let bytes: Vec<u8> = (0..len)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 17;
                    x ^= x << 5;
                    (x as u8) | (0xF0 * u8::from(x & 0x100 != 0))
                })
                .collect();
            let _ = parse(&bytes, true);
        }
    }

    #[test]
    fn varint_lengths() {
        for v in [0usize, 1, 127, 128, 300, 16383, 16384, 1 << 30] {
            let mut out = Vec::new();
            write_varint(&mut out, v);
            assert_eq!(out.len(), varint_len(v), "{v}");
            let mut at = 0;
            assert_eq!(read_varint(&out, &mut at).unwrap() as usize, v);
        }
    }

    #[test]
    fn owned_children_partition_every_level() {
        for domain in [
            IdSpace::Planar(PlanarDomain::new(5).unwrap()),
            IdSpace::Sphere(SphereDomain::new(3).unwrap()),
        ] {
            let roots: Vec<[i64; 3]> = match domain {
                IdSpace::Planar(d) => vec![[d.root().x, d.root().y, 0]],
                IdSpace::Sphere(d) => d.roots().iter().map(|r| r.c).collect(),
            };
            // Each diamond of the next level is owned exactly once, by its first parent.
            let mut level = roots;
            for _ in 0..4 {
                let mut next = Vec::new();
                for &c in &level {
                    for k in domain.owned_children(c).unwrap() {
                        assert_eq!(domain.owner(k).unwrap(), Some(c));
                        next.push(k);
                    }
                }
                let mut all: Vec<[i64; 3]> = Vec::new();
                for &c in &level {
                    let children: Vec<[i64; 3]> = match domain {
                        IdSpace::Planar(d) => d
                            .children(planar(c))
                            .unwrap()
                            .iter()
                            .map(|k| [k.x, k.y, 0])
                            .collect(),
                        IdSpace::Sphere(d) => d
                            .children(SphereId { c })
                            .unwrap()
                            .iter()
                            .map(|k| k.c)
                            .collect(),
                    };
                    all.extend(children);
                }
                all.sort();
                all.dedup();
                next.sort();
                assert_eq!(next, all, "every child owned exactly once");
                level = next;
            }
        }
    }
}

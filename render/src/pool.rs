//! The bookkeeping of the GPU patch pool, without the GPU: which patch lives in which
//! equal-sized slot, which slots hold patches that left the cut recently (an LRU cache a
//! returning patch is drawn from again without an upload), and which are free.
//!
//! Slots are allocated in O(1) from a free list, or by evicting the least recently
//! released cached patch; a wanted patch (one the renderer draws or is about to) is never
//! evicted. The number of slots is fixed when the pool is made (from the byte budget), so
//! the budget can never be exceeded: when every slot holds a wanted patch, [`Pool::want`]
//! says so ([`Placement::Full`]) and the renderer draws without that patch.

use std::collections::{BTreeMap, HashMap};
use std::hash::Hash;

/// Where a wanted patch lives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Placement {
    /// Its data is in this slot already (it was cached, or wanted twice).
    Resident(u32),
    /// This slot is its own now; write its data there, then call [`Pool::written`].
    Upload(u32),
    /// Every slot holds a wanted patch: nothing was allocated.
    Full,
}

#[derive(Clone, Copy, Debug)]
struct Entry {
    slot: u32,
    /// Drawn or about to be: never evicted.
    wanted: bool,
    /// The slot holds the patch's data.
    written: bool,
    /// Its LRU stamp while cached (not wanted, written).
    stamp: u64,
}

/// Slot bookkeeping for patches named by `K`.
#[derive(Debug)]
pub struct Pool<K> {
    capacity: u32,
    entries: HashMap<K, Entry>,
    /// Cached patches by release stamp, oldest first.
    lru: BTreeMap<u64, K>,
    /// Slots never used or freed.
    free: Vec<u32>,
    /// Slots handed out so far (slots above it were never used).
    high_water: u32,
    clock: u64,
    /// Counters.
    stats: PoolStats,
}

/// What the pool did (cumulative).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PoolStats {
    /// Slots handed out for uploads.
    pub uploads: u64,
    /// Wanted patches found in the cache (no upload).
    pub cache_hits: u64,
    /// Cached patches evicted to make room.
    pub evictions: u64,
    /// Requests refused because every slot was wanted.
    pub full: u64,
}

impl<K: Hash + Eq + Clone> Pool<K> {
    /// A pool of `capacity` slots.
    pub fn new(capacity: u32) -> Pool<K> {
        Pool {
            capacity,
            entries: HashMap::new(),
            lru: BTreeMap::new(),
            free: Vec::new(),
            high_water: 0,
            clock: 0,
            stats: PoolStats::default(),
        }
    }

    /// Number of slots.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Slots holding a patch (wanted or cached) or allocated for an upload.
    pub fn occupied(&self) -> usize {
        self.entries.len()
    }

    /// Patches cached (released, data kept).
    pub fn cached(&self) -> usize {
        self.lru.len()
    }

    /// Counters since the pool was made.
    pub fn stats(&self) -> PoolStats {
        self.stats
    }

    /// The slot of a patch the pool holds (wanted or cached).
    pub fn slot(&self, key: &K) -> Option<u32> {
        self.entries.get(key).map(|e| e.slot)
    }

    /// Whether the patch is wanted and its data is in its slot.
    pub fn is_ready(&self, key: &K) -> bool {
        self.entries.get(key).is_some_and(|e| e.wanted && e.written)
    }

    /// Marks a patch wanted: from the cache, a free slot, or the least recently released
    /// cached patch's slot.
    pub fn want(&mut self, key: K) -> Placement {
        if let Some(e) = self.entries.get_mut(&key) {
            if !e.wanted {
                e.wanted = true;
                self.lru.remove(&e.stamp);
                self.stats.cache_hits += 1;
            }
            return if e.written {
                Placement::Resident(e.slot)
            } else {
                Placement::Upload(e.slot)
            };
        }
        let slot = if let Some(slot) = self.free.pop() {
            slot
        } else if self.high_water < self.capacity {
            self.high_water += 1;
            self.high_water - 1
        } else if let Some((_, old)) = self.lru.pop_first() {
            self.stats.evictions += 1;
            match self.entries.remove(&old) {
                Some(e) => e.slot,
                None => return Placement::Full,
            }
        } else {
            self.stats.full += 1;
            return Placement::Full;
        };
        self.stats.uploads += 1;
        self.entries.insert(
            key,
            Entry {
                slot,
                wanted: true,
                written: false,
                stamp: 0,
            },
        );
        Placement::Upload(slot)
    }

    /// Records that a wanted patch's data is in its slot.
    pub fn written(&mut self, key: &K) {
        if let Some(e) = self.entries.get_mut(key) {
            e.written = true;
        }
    }

    /// The patch is no longer wanted: its slot is cached if it holds its data (the most
    /// recently released is evicted last), freed otherwise.
    pub fn release(&mut self, key: &K) {
        let Some(e) = self.entries.get_mut(key) else {
            return;
        };
        if !e.wanted {
            return;
        }
        if e.written {
            e.wanted = false;
            self.clock += 1;
            e.stamp = self.clock;
            self.lru.insert(self.clock, key.clone());
        } else {
            let slot = e.slot;
            self.entries.remove(key);
            self.free.push(slot);
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::HashSet;

    /// The naive model: a list of (key, slot, written) in release order for the cache.
    #[derive(Default)]
    struct Model {
        wanted: HashMap<u16, (u32, bool)>,
        cached: Vec<(u16, u32)>, // oldest first
        free: Vec<u32>,
        next: u32,
    }

    #[derive(Clone, Debug)]
    enum Op {
        Want(u16),
        Write(u16),
        Release(u16),
    }

    fn ops() -> impl Strategy<Value = Vec<Op>> {
        proptest::collection::vec(
            prop_oneof![
                (0u16..40).prop_map(Op::Want),
                (0u16..40).prop_map(Op::Write),
                (0u16..40).prop_map(Op::Release),
            ],
            0..400,
        )
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        /// Random want/write/release sequences against the naive model: same placements,
        /// never more slots than the capacity, no slot shared by two patches, and a
        /// patch that left and came back while cached is not uploaded again.
        #[test]
        fn pool_matches_a_naive_model(capacity in 1u32..24, ops in ops()) {
            let mut pool: Pool<u16> = Pool::new(capacity);
            let mut model = Model::default();
            for op in ops {
                match op {
                    Op::Want(k) => {
                        let expect = if let Some(&(slot, written)) = model.wanted.get(&k) {
                            if written { Placement::Resident(slot) } else { Placement::Upload(slot) }
                        } else if let Some(pos) = model.cached.iter().position(|c| c.0 == k) {
                            let (_, slot) = model.cached.remove(pos);
                            model.wanted.insert(k, (slot, true));
                            Placement::Resident(slot)
                        } else {
                            let slot = if let Some(s) = model.free.pop() {
                                Some(s)
                            } else if model.next < capacity {
                                model.next += 1;
                                Some(model.next - 1)
                            } else if !model.cached.is_empty() {
                                Some(model.cached.remove(0).1)
                            } else {
                                None
                            };
                            match slot {
                                Some(s) => {
                                    model.wanted.insert(k, (s, false));
                                    Placement::Upload(s)
                                }
                                None => Placement::Full,
                            }
                        };
                        prop_assert_eq!(pool.want(k), expect);
                    }
                    Op::Write(k) => {
                        if let Some(w) = model.wanted.get_mut(&k) {
                            w.1 = true;
                            pool.written(&k);
                        }
                    }
                    Op::Release(k) => {
                        if let Some((slot, written)) = model.wanted.remove(&k) {
                            if written {
                                model.cached.push((k, slot));
                            } else {
                                model.free.push(slot);
                            }
                        }
                        pool.release(&k);
                    }
                }
                // The budget: never more slots than the capacity, each slot one patch.
                let slots: Vec<u32> = model
                    .wanted
                    .values()
                    .map(|w| w.0)
                    .chain(model.cached.iter().map(|c| c.1))
                    .collect();
                let distinct: HashSet<u32> = slots.iter().copied().collect();
                prop_assert_eq!(distinct.len(), slots.len());
                prop_assert!(slots.iter().all(|&s| s < capacity));
                prop_assert_eq!(pool.occupied(), slots.len());
                prop_assert_eq!(pool.cached(), model.cached.len());
                for (k, (slot, written)) in &model.wanted {
                    prop_assert_eq!(pool.slot(k), Some(*slot));
                    prop_assert_eq!(pool.is_ready(k), *written);
                }
            }
        }
    }

    #[test]
    fn a_returning_patch_is_not_uploaded_again_while_cached() {
        let mut pool: Pool<u32> = Pool::new(2);
        assert_eq!(pool.want(1), Placement::Upload(0));
        pool.written(&1);
        pool.release(&1);
        assert_eq!(pool.want(1), Placement::Resident(0));
        assert_eq!(pool.stats().uploads, 1);
        assert_eq!(pool.stats().cache_hits, 1);
        // Both slots wanted: a third patch is refused, nothing is evicted.
        assert_eq!(pool.want(2), Placement::Upload(1));
        assert_eq!(pool.want(3), Placement::Full);
        // Released and cached: the oldest cached patch gives its slot.
        pool.written(&2);
        pool.release(&1);
        pool.release(&2);
        assert_eq!(pool.want(3), Placement::Upload(0));
        assert_eq!(pool.want(2), Placement::Resident(1));
        assert_eq!(pool.stats().evictions, 1);
    }
}

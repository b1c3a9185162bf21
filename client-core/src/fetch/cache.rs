//! The decoded-value cache: least recently used values evicted past a byte budget, plus the
//! set of keys known to be leaves (empty blobs), which is never evicted so a leaf is never
//! requested twice.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::Arc;

use super::{Key, Weigh};

struct Entry<T> {
    value: Arc<T>,
    weight: usize,
    /// Position in the recency order (larger = used more recently).
    tick: u64,
}

/// An LRU cache of decoded values with a byte budget, and a set of leaf keys.
///
/// Invariants: `used_bytes() <= budget_bytes()`; a key is never both cached and a leaf.
pub struct DecodedCache<T> {
    budget_bytes: usize,
    used_bytes: usize,
    entries: HashMap<Key, Entry<T>>,
    /// Recency order: tick -> key, oldest first.
    order: BTreeMap<u64, Key>,
    next_tick: u64,
    leaves: HashSet<Key>,
}

impl<T: Weigh> DecodedCache<T> {
    /// An empty cache holding at most `budget_bytes` of values.
    pub fn new(budget_bytes: usize) -> Self {
        DecodedCache {
            budget_bytes,
            used_bytes: 0,
            entries: HashMap::new(),
            order: BTreeMap::new(),
            next_tick: 0,
            leaves: HashSet::new(),
        }
    }

    /// The byte budget.
    pub fn budget_bytes(&self) -> usize {
        self.budget_bytes
    }

    /// Bytes held by cached values.
    pub fn used_bytes(&self) -> usize {
        self.used_bytes
    }

    /// Cached values.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether no value is cached.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Known leaves.
    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
    }

    /// The value of `key`, marking it most recently used.
    pub fn get(&mut self, key: Key) -> Option<Arc<T>> {
        let tick = self.next_tick;
        let entry = self.entries.get_mut(&key)?;
        self.order.remove(&entry.tick);
        entry.tick = tick;
        self.order.insert(tick, key);
        self.next_tick += 1;
        Some(Arc::clone(&entry.value))
    }

    /// A frame's requests against what is held: the wants answered here (`None`: a
    /// leaf), the wants to ask for, and the prefetch keys neither held nor leaves.
    #[allow(clippy::type_complexity)]
    pub fn answer_held(
        &mut self,
        wants: Vec<(Key, f32)>,
        prefetch: Vec<(Key, f32)>,
    ) -> (Vec<(Key, Option<Arc<T>>)>, Vec<(Key, f32)>, Vec<(Key, f32)>) {
        let mut held = Vec::new();
        let mut ask = Vec::with_capacity(wants.len());
        for (k, p) in wants {
            if self.is_leaf(k) {
                held.push((k, None));
            } else if let Some(v) = self.get(k) {
                held.push((k, Some(v)));
            } else {
                ask.push((k, p));
            }
        }
        let prefetch = prefetch
            .into_iter()
            .filter(|&(k, _)| !self.is_leaf(k) && !self.contains(k))
            .collect();
        (held, ask, prefetch)
    }

    /// Whether `key` is cached, without touching its recency.
    pub fn contains(&self, key: Key) -> bool {
        self.entries.contains_key(&key)
    }

    /// Caches `value` as the most recently used, evicting the least recently used values
    /// until it fits (and forgets that `key` was a leaf). A value larger than the whole
    /// budget is not cached. Returns the evicted keys.
    pub fn insert(&mut self, key: Key, value: Arc<T>) -> Vec<Key> {
        self.remove(key);
        self.leaves.remove(&key);
        let weight = value.weight_bytes();
        if weight > self.budget_bytes {
            return Vec::new();
        }
        let mut evicted = Vec::new();
        while self.used_bytes + weight > self.budget_bytes {
            let Some((_, oldest)) = self.order.pop_first() else {
                break;
            };
            if let Some(e) = self.entries.remove(&oldest) {
                self.used_bytes -= e.weight;
            }
            evicted.push(oldest);
        }
        let tick = self.next_tick;
        self.next_tick += 1;
        self.order.insert(tick, key);
        self.entries.insert(
            key,
            Entry {
                value,
                weight,
                tick,
            },
        );
        self.used_bytes += weight;
        evicted
    }

    /// Drops `key`'s value; whether it was cached.
    pub fn remove(&mut self, key: Key) -> bool {
        match self.entries.remove(&key) {
            Some(e) => {
                self.order.remove(&e.tick);
                self.used_bytes -= e.weight;
                true
            }
            None => false,
        }
    }

    /// Records that `key` is a leaf (and drops any value cached for it).
    pub fn mark_leaf(&mut self, key: Key) {
        self.remove(key);
        self.leaves.insert(key);
    }

    /// Whether `key` is a known leaf.
    pub fn is_leaf(&self, key: Key) -> bool {
        self.leaves.contains(&key)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::expect_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A value that weighs what it says.
    #[derive(Debug, PartialEq)]
    struct W(usize);

    impl Weigh for W {
        fn weight_bytes(&self) -> usize {
            self.0
        }
    }

    /// The naive model: a list ordered from least to most recently used.
    #[derive(Default)]
    struct Model {
        budget: usize,
        lru: Vec<(Key, usize)>,
        leaves: Vec<Key>,
    }

    impl Model {
        fn used(&self) -> usize {
            self.lru.iter().map(|(_, w)| w).sum()
        }
        fn get(&mut self, k: Key) -> Option<usize> {
            let i = self.lru.iter().position(|(x, _)| *x == k)?;
            let e = self.lru.remove(i);
            self.lru.push(e);
            Some(e.1)
        }
        fn remove(&mut self, k: Key) -> bool {
            let before = self.lru.len();
            self.lru.retain(|(x, _)| *x != k);
            before != self.lru.len()
        }
        fn insert(&mut self, k: Key, w: usize) -> Vec<Key> {
            self.remove(k);
            self.leaves.retain(|x| *x != k);
            if w > self.budget {
                return vec![];
            }
            let mut evicted = vec![];
            while self.used() + w > self.budget {
                evicted.push(self.lru.remove(0).0);
            }
            self.lru.push((k, w));
            evicted
        }
        fn mark_leaf(&mut self, k: Key) {
            self.remove(k);
            if !self.leaves.contains(&k) {
                self.leaves.push(k);
            }
        }
    }

    #[derive(Clone, Debug)]
    enum Op {
        Get(i64),
        Insert(i64, usize),
        Remove(i64),
        Leaf(i64),
    }

    fn op() -> impl Strategy<Value = Op> {
        let key = 0i64..12;
        prop_oneof![
            key.clone().prop_map(Op::Get),
            (key.clone(), 0usize..400).prop_map(|(k, w)| Op::Insert(k, w)),
            key.clone().prop_map(Op::Remove),
            key.prop_map(Op::Leaf),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        #[test]
        fn the_cache_behaves_like_a_naive_lru_list(
            budget in 0usize..1200,
            ops in proptest::collection::vec(op(), 0..200),
        ) {
            let mut cache = DecodedCache::<W>::new(budget);
            let mut model = Model { budget, ..Model::default() };
            for op in ops {
                match op {
                    Op::Get(k) => {
                        let key = [k, 0, 0];
                        prop_assert_eq!(cache.get(key).map(|v| v.0), model.get(key));
                    }
                    Op::Insert(k, w) => {
                        let key = [k, 0, 0];
                        let mut got = cache.insert(key, Arc::new(W(w)));
                        let mut want = model.insert(key, w);
                        got.sort_unstable();
                        want.sort_unstable();
                        prop_assert_eq!(got, want);
                    }
                    Op::Remove(k) => {
                        prop_assert_eq!(cache.remove([k, 0, 0]), model.remove([k, 0, 0]));
                    }
                    Op::Leaf(k) => {
                        cache.mark_leaf([k, 0, 0]);
                        model.mark_leaf([k, 0, 0]);
                    }
                }
                prop_assert_eq!(cache.used_bytes(), model.used());
                prop_assert!(cache.used_bytes() <= budget);
                prop_assert_eq!(cache.len(), model.lru.len());
                prop_assert_eq!(cache.leaf_count(), model.leaves.len());
                for k in 0..12 {
                    let key = [k, 0, 0];
                    prop_assert_eq!(cache.is_leaf(key), model.leaves.contains(&key));
                    prop_assert_eq!(
                        cache.contains(key),
                        model.lru.iter().any(|(x, _)| *x == key)
                    );
                    prop_assert!(!(cache.is_leaf(key) && cache.contains(key)));
                }
            }
        }
    }

    #[test]
    fn a_value_larger_than_the_budget_is_not_cached() {
        let mut c = DecodedCache::new(10);
        assert!(c.insert([1, 0, 0], Arc::new(W(5))).is_empty());
        assert!(c.insert([2, 0, 0], Arc::new(W(11))).is_empty());
        assert!(c.contains([1, 0, 0]) && !c.contains([2, 0, 0]));
    }

    #[test]
    fn getting_a_value_protects_it_from_eviction() {
        let mut c = DecodedCache::new(30);
        for k in 0..3 {
            c.insert([k, 0, 0], Arc::new(W(10)));
        }
        c.get([0, 0, 0]);
        assert_eq!(c.insert([9, 0, 0], Arc::new(W(10))), vec![[1, 0, 0]]);
    }
}

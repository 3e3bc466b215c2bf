//! A pool of GPU buffers handed to tiles as they are drawn, least recently used first: the
//! GeoMipMaps paper's VBO manager (Brodersen 2005, section 5).
//!
//! A tile about to be drawn without a buffer takes a free one, or else the least recently
//! used one, whose owner loses it (and is uploaded again when it is next drawn). No buffer
//! is handed out twice in one frame: when every buffer has been used this frame, a new one is
//! made and the pool grows to what the frame needs. When a frame uses fewer buffers than the
//! pool holds, the next frame drops one unused buffer, so the pool shrinks slowly back to
//! what the frames need. GPU memory thus goes to the tiles that are drawn, not to every
//! resident tile.
//!
//! The pool is generic over what a slot holds (the renderer keeps a storage buffer and its
//! bind group) so that its rules are tested without a GPU.

use std::collections::HashMap;
use std::hash::Hash;

/// One buffer of the pool.
#[derive(Debug)]
struct Slot<K, T> {
    value: T,
    owner: Option<K>,
    /// Frame it was last handed out in (0: never).
    last_used: u64,
}

/// How [`LruPool::acquire`] served a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Acquired<K> {
    /// The key already held this slot: its contents are current.
    Kept(usize),
    /// A slot taken from its least recently used owner (`evicted`), or a free one (`None`);
    /// the caller fills it.
    Reused { slot: usize, evicted: Option<K> },
    /// A new slot: every other one was in use this frame. The caller fills it.
    Grown(usize),
}

impl<K> Acquired<K> {
    /// The slot handed out.
    pub fn slot(&self) -> usize {
        match *self {
            Acquired::Kept(slot) | Acquired::Reused { slot, .. } | Acquired::Grown(slot) => slot,
        }
    }

    /// Whether the caller must fill the slot with its key's data.
    pub fn needs_upload(&self) -> bool {
        !matches!(self, Acquired::Kept(_))
    }
}

/// The pool; see the module documentation.
#[derive(Debug)]
pub struct LruPool<K, T> {
    slots: Vec<Slot<K, T>>,
    owners: HashMap<K, usize>,
    frame: u64,
    /// Slots handed out in the current frame.
    used: usize,
}

impl<K: Copy + Eq + Hash, T> Default for LruPool<K, T> {
    fn default() -> Self {
        LruPool {
            slots: Vec::new(),
            owners: HashMap::new(),
            frame: 0,
            used: 0,
        }
    }
}

impl<K: Copy + Eq + Hash, T> LruPool<K, T> {
    /// Slots the pool holds (in use or not).
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Slots handed out in the current frame.
    pub fn used_this_frame(&self) -> usize {
        self.used
    }

    /// The slot `key` holds, if any.
    pub fn slot_of(&self, key: K) -> Option<usize> {
        self.owners.get(&key).copied()
    }

    pub fn get(&self, slot: usize) -> &T {
        &self.slots[slot].value
    }

    /// Every slot's value, in slot order.
    pub fn values_mut(&mut self) -> impl Iterator<Item = &mut T> {
        self.slots.iter_mut().map(|s| &mut s.value)
    }

    /// Starts a frame. If the last frame used fewer slots than the pool holds, one slot it
    /// did not use (a free one first, else the least recently used) is dropped and
    /// returned, with the owner that loses it: the pool shrinks one slot a frame.
    pub fn begin_frame(&mut self) -> Option<(T, Option<K>)> {
        let shrink = self.frame > 0 && self.used < self.slots.len();
        self.frame += 1;
        self.used = 0;
        if !shrink {
            return None;
        }
        let victim = (0..self.slots.len())
            .filter(|&i| self.slots[i].last_used < self.frame - 1)
            .min_by_key(|&i| (self.slots[i].owner.is_some(), self.slots[i].last_used))?;
        Some(self.remove(victim))
    }

    /// Hands `key` a slot for the current frame (see [`Acquired`]); `make` builds a new slot
    /// when the pool must grow. Never hands out a slot already handed out this frame to
    /// another key.
    pub fn acquire(&mut self, key: K, make: impl FnOnce() -> T) -> Acquired<K> {
        let frame = self.frame;
        if let Some(&slot) = self.owners.get(&key) {
            if self.slots[slot].last_used != frame {
                self.used += 1;
            }
            self.slots[slot].last_used = frame;
            return Acquired::Kept(slot);
        }
        self.used += 1;
        let free = (0..self.slots.len())
            .filter(|&i| self.slots[i].last_used < frame)
            .min_by_key(|&i| (self.slots[i].owner.is_some(), self.slots[i].last_used));
        match free {
            Some(slot) => {
                let evicted = self.slots[slot].owner.replace(key);
                if let Some(old) = evicted {
                    self.owners.remove(&old);
                }
                self.slots[slot].last_used = frame;
                self.owners.insert(key, slot);
                Acquired::Reused { slot, evicted }
            }
            None => {
                self.slots.push(Slot {
                    value: make(),
                    owner: Some(key),
                    last_used: frame,
                });
                let slot = self.slots.len() - 1;
                self.owners.insert(key, slot);
                Acquired::Grown(slot)
            }
        }
    }

    /// `key` is gone (its tile was evicted): its slot becomes free, and is dropped at once
    /// when the pool holds more slots than `keep`.
    pub fn release(&mut self, key: K, keep: usize) -> Option<T> {
        let slot = self.owners.remove(&key)?;
        self.slots[slot].owner = None;
        (self.slots.len() > keep).then(|| self.remove(slot).0)
    }

    /// Drops `slot`, keeping the other slots' indices valid for their owners.
    fn remove(&mut self, slot: usize) -> (T, Option<K>) {
        let removed = self.slots.swap_remove(slot);
        if let Some(owner) = removed.owner {
            self.owners.remove(&owner);
        }
        if let Some(moved) = self.slots.get(slot).and_then(|s| s.owner) {
            self.owners.insert(moved, slot);
        }
        (removed.value, removed.owner)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_drawn_key_keeps_its_slot_and_the_least_recently_used_one_is_taken() {
        let mut pool: LruPool<u32, u32> = LruPool::default();
        let mut made = 0;
        let mut make = || {
            made += 1;
            made
        };
        pool.begin_frame();
        assert_eq!(pool.acquire(1, &mut make), Acquired::Grown(0));
        assert_eq!(pool.acquire(2, &mut make), Acquired::Grown(1));
        assert_eq!(pool.acquire(3, &mut make), Acquired::Grown(2));
        pool.begin_frame();
        assert_eq!(pool.acquire(2, &mut make), Acquired::Kept(1));
        assert_eq!(pool.acquire(3, &mut make), Acquired::Kept(2));
        // Slot 0 (key 1, last used in frame 1) is the only one not used this frame.
        assert_eq!(
            pool.acquire(4, &mut make),
            Acquired::Reused {
                slot: 0,
                evicted: Some(1)
            }
        );
        // Every slot is in use this frame: a fifth key grows the pool.
        assert_eq!(pool.acquire(5, &mut make), Acquired::Grown(3));
        assert_eq!(pool.slot_of(1), None);
        assert_eq!(pool.slot_of(4), Some(0));
        assert_eq!(made, 4);
    }

    #[test]
    fn a_frame_needing_more_slots_grows_the_pool_and_fewer_shrink_it_one_a_frame() {
        let mut pool: LruPool<u32, ()> = LruPool::default();
        pool.begin_frame();
        for k in 0..5 {
            pool.acquire(k, || ());
        }
        assert_eq!(pool.len(), 5);
        // Two keys a frame from now on: from the frame after the first that needed less, the
        // pool shrinks by one a frame down to two.
        let mut sizes = Vec::new();
        for _ in 0..5 {
            pool.begin_frame();
            pool.acquire(0, || ());
            pool.acquire(1, || ());
            sizes.push(pool.len());
        }
        assert_eq!(sizes, vec![5, 4, 3, 2, 2]);
        assert_eq!(pool.slot_of(0).map(|s| s < 2), Some(true));
    }

    #[test]
    fn a_released_key_frees_its_slot_and_a_pool_over_its_keep_drops_it() {
        let mut pool: LruPool<u32, ()> = LruPool::default();
        pool.begin_frame();
        pool.acquire(7, || ());
        pool.acquire(8, || ());
        assert!(pool.release(7, 2).is_none(), "kept as a free slot");
        assert_eq!(pool.len(), 2);
        pool.begin_frame();
        assert_eq!(
            pool.acquire(9, || ()),
            Acquired::Reused {
                slot: 0,
                evicted: None
            }
        );
        assert!(pool.release(9, 1).is_some(), "over the keep: dropped");
        assert_eq!(pool.len(), 1);
        assert_eq!(pool.slot_of(8), Some(0), "the moved slot keeps its owner");
    }

    proptest! {
        /// Over any sequence of frames, keys and evictions: no slot goes to two keys in one
        /// frame, a slot kept by a key still holds that key's data, and the pool never holds
        /// more slots than the most one frame needed.
        #[test]
        fn no_slot_serves_two_keys_in_a_frame(
            frames in proptest::collection::vec(
                (proptest::collection::vec(0u32..12, 0..10), proptest::option::of(0u32..12)),
                1..40,
            )
        ) {
            // Each slot holds the key it was last filled for, as a renderer's buffer would.
            let mut pool: LruPool<u32, u32> = LruPool::default();
            let mut most = 0;
            for (keys, evict) in frames {
                pool.begin_frame();
                if let Some(k) = evict {
                    pool.release(k, 12);
                }
                let mut served: HashMap<usize, u32> = HashMap::new();
                for &k in &keys {
                    let got = pool.acquire(k, || u32::MAX);
                    let slot = got.slot();
                    if let Some(&other) = served.get(&slot) {
                        prop_assert_eq!(other, k, "slot {} served two keys in a frame", slot);
                    }
                    served.insert(slot, k);
                    if got.needs_upload() {
                        pool.slots[slot].value = k;
                    }
                    prop_assert_eq!(*pool.get(slot), k, "the slot holds the key's data");
                    prop_assert_eq!(pool.slot_of(k), Some(slot));
                }
                let distinct: std::collections::HashSet<u32> = keys.iter().copied().collect();
                prop_assert_eq!(pool.used_this_frame(), distinct.len());
                most = most.max(distinct.len());
                prop_assert!(pool.len() >= distinct.len());
                prop_assert!(pool.len() <= most, "{} slots, at most {} needed", pool.len(), most);
            }
        }
    }
}

//! The block cache: what the runtime holds in memory of the aggregates it traces, bounded by a
//! byte budget shared by every aggregate and every instance of a scene.
//!
//! An aggregate's levels are stored as blocks of voxels and of boundary faces (a Morton range
//! each: at most 1024 voxels in bakes of this version, 4096 before; see
//! `bake::BLOCK_VOXELS`). A level keeps only its skeleton resident (the occupancy
//! hierarchy, the bricks and the block ranges: a few bytes a voxel); a block is inflated, verified and prepared (hit and weight records, the ABSDFs of
//! the voxels shaded) the first time a cone needs it, into a slot of its level, and stays
//! there until the cache evicts it. Eviction is CLOCK (second chance): every access sets the
//! slot's reference bit, and the hand clears bits until it finds a slot not referenced since
//! its last pass, whose block it drops. A cone holds the blocks it uses by reference count,
//! so eviction never frees a block in use; it is freed when the last cone lets go.
//!
//! The bytes counted are those of every prepared block alive, in the cache or held by a
//! cone: its records, its inflated bytes and the ABSDFs built in it. Whatever the budget, a
//! block is prepared from the same bytes the same way, so a render under any budget gives the
//! same image bits; a budget smaller than the working set only costs time (blocks prepared
//! again after eviction). Room is made before a block is prepared (as much as the largest
//! block prepared so far, for each block being prepared on any thread), so that the bytes
//! alive stay within the budget; blocks that cones hold can still take them over it.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex, OnceLock};

/// Something the cache can evict: a slot of a level.
pub(crate) trait Evictable: Send + Sync {
    /// Clears the reference bit; whether it was set.
    fn take_referenced(&self) -> bool;
    /// Drops the slot's block unless a loader holds the slot now; whether the slot is empty
    /// afterwards (evicted or already empty).
    fn evict(&self) -> bool;
    /// Whether the slot holds no block (nothing to evict: its ring entry can go).
    fn is_empty(&self) -> bool;
}

/// What the cache has done so far ([`BlockCache::stats`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct CacheStats {
    /// The budget in bytes.
    pub budget: u64,
    /// Blocks prepared (a block evicted and needed again counts again).
    pub loaded: u64,
    /// Distinct blocks prepared (each counted once however often it was prepared again).
    pub distinct: u64,
    /// Bytes counted by all the preparations (records, inflated bytes, ABSDFs built), for the
    /// mean bytes a block prepared costs.
    pub prepared_bytes: u64,
    /// Blocks evicted.
    pub evicted: u64,
    /// Bytes of the prepared blocks alive now.
    pub bytes: u64,
    /// The most bytes alive at once.
    pub peak: u64,
}

impl CacheStats {
    /// The bytes the distinct blocks prepared would hold at once (their count times the mean
    /// bytes of a preparation): about the budget under which a view prepares each block once.
    pub fn working_set(&self) -> u64 {
        if self.loaded == 0 {
            return 0;
        }
        (self.prepared_bytes as f64 / self.loaded as f64 * self.distinct as f64) as u64
    }

    /// Whether blocks were prepared again after eviction often enough to cost time: more than
    /// 1.2 preparations a distinct block.
    pub fn reloads(&self) -> bool {
        self.evicted > 0 && self.loaded as f64 > 1.2 * self.distinct as f64
    }
}

/// A byte budget for the prepared blocks of any number of aggregates, with CLOCK eviction.
/// [`BlockCache::global`] is the one every aggregate opened without a cache of its own shares.
pub struct BlockCache {
    budget: AtomicU64,
    bytes: AtomicU64,
    peak: AtomicU64,
    /// The largest single growth seen (a block prepared): the room made before preparing
    /// the next one.
    largest: AtomicU64,
    /// Blocks being prepared now, on any thread.
    preparing: AtomicU64,
    loaded: AtomicU64,
    distinct: AtomicU64,
    prepared_bytes: AtomicU64,
    /// Which statistics these are (1, then one more at each [`BlockCache::reset_stats`]): a
    /// slot counts in `distinct` once per epoch.
    epoch: AtomicU64,
    evicted: AtomicU64,
    ring: Mutex<Ring>,
}

struct Ring {
    slots: Vec<Arc<dyn Evictable>>,
    hand: usize,
}

/// The default budget: a quarter of the machine's physical memory (1 GiB where it cannot be
/// read), at least 64 MiB.
pub fn default_budget() -> u64 {
    // SAFETY: sysconf has no preconditions.
    let (pages, page) = unsafe {
        (
            libc::sysconf(libc::_SC_PHYS_PAGES),
            libc::sysconf(libc::_SC_PAGESIZE),
        )
    };
    let total = if pages > 0 && page > 0 {
        pages as u64 * page as u64
    } else {
        4 << 30
    };
    (total / 4).max(64 << 20)
}

impl BlockCache {
    /// A cache of `budget` bytes.
    pub fn new(budget: u64) -> Arc<BlockCache> {
        Arc::new(BlockCache {
            budget: AtomicU64::new(budget),
            bytes: AtomicU64::new(0),
            peak: AtomicU64::new(0),
            largest: AtomicU64::new(0),
            preparing: AtomicU64::new(0),
            loaded: AtomicU64::new(0),
            distinct: AtomicU64::new(0),
            prepared_bytes: AtomicU64::new(0),
            epoch: AtomicU64::new(1),
            evicted: AtomicU64::new(0),
            ring: Mutex::new(Ring {
                slots: Vec::new(),
                hand: 0,
            }),
        })
    }

    /// The process's shared cache, of [`default_budget`] bytes until
    /// [`BlockCache::set_budget`] changes it.
    pub fn global() -> &'static Arc<BlockCache> {
        static GLOBAL: OnceLock<Arc<BlockCache>> = OnceLock::new();
        GLOBAL.get_or_init(|| BlockCache::new(default_budget()))
    }

    /// Sets the budget in bytes; blocks over it are evicted now.
    pub fn set_budget(&self, budget: u64) {
        self.budget.store(budget, Relaxed);
        self.evict_over_budget();
    }

    /// The budget in bytes.
    pub fn budget(&self) -> u64 {
        self.budget.load(Relaxed)
    }

    /// What the cache has done so far.
    pub fn stats(&self) -> CacheStats {
        CacheStats {
            budget: self.budget(),
            loaded: self.loaded.load(Relaxed),
            distinct: self.distinct.load(Relaxed),
            prepared_bytes: self.prepared_bytes.load(Relaxed),
            evicted: self.evicted.load(Relaxed),
            bytes: self.bytes.load(Relaxed),
            peak: self.peak.load(Relaxed),
        }
    }

    /// Starts the statistics afresh (loaded, distinct, evicted, peak; the bytes alive stay).
    pub fn reset_stats(&self) {
        self.loaded.store(0, Relaxed);
        self.distinct.store(0, Relaxed);
        self.prepared_bytes.store(0, Relaxed);
        self.epoch.fetch_add(1, Relaxed);
        self.evicted.store(0, Relaxed);
        self.peak.store(self.bytes.load(Relaxed), Relaxed);
    }

    /// `n` more bytes alive (a block prepared, an ABSDF built in one).
    pub(crate) fn grow(&self, n: u64) {
        self.prepared_bytes.fetch_add(n, Relaxed);
        let now = self.bytes.fetch_add(n, Relaxed) + n;
        self.peak.fetch_max(now, Relaxed);
        self.largest.fetch_max(n, Relaxed);
    }

    /// Evicts before a block is prepared until it fits beside the others being prepared,
    /// each counted as large as the largest block so far, so that the bytes alive stay within
    /// the budget instead of going over it by the blocks being prepared (blocks that cones
    /// hold can still take them over). The reservation lasts as long as the guard.
    pub(crate) fn make_room(&self) -> Room<'_> {
        let budget = self.budget();
        let n = self.preparing.fetch_add(1, Relaxed) + 1;
        let reserve = self.largest.load(Relaxed).saturating_mul(n).min(budget);
        self.evict_to(budget - reserve);
        Room(self)
    }

    /// `n` bytes freed (a block dropped).
    pub(crate) fn shrink(&self, n: u64) {
        self.bytes.fetch_sub(n, Relaxed);
    }

    /// A slot that just received a block: counted, put on the ring, and room made.
    /// `counted` is the epoch the slot last counted in `distinct` (swapped for this one).
    pub(crate) fn inserted(&self, slot: Arc<dyn Evictable>, counted: &AtomicU64) {
        self.loaded.fetch_add(1, Relaxed);
        let epoch = self.epoch.load(Relaxed);
        if counted.swap(epoch, Relaxed) != epoch {
            self.distinct.fetch_add(1, Relaxed);
        }
        self.ring
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .slots
            .push(slot);
        self.evict_over_budget();
    }

    /// Evicts by CLOCK until the bytes alive are within the budget or nothing on the ring can
    /// be evicted (every block left is in use or being loaded).
    pub(crate) fn evict_over_budget(&self) {
        self.evict_to(self.budget());
    }

    /// Evicts by CLOCK until the bytes alive are at most `limit` or nothing on the ring can
    /// be evicted.
    fn evict_to(&self, limit: u64) {
        if self.bytes.load(Relaxed) <= limit {
            return;
        }
        let mut ring = self.ring.lock().unwrap_or_else(|p| p.into_inner());
        // Two passes over the ring at most: the first may only clear reference bits.
        let mut visits = 2 * ring.slots.len() + 1;
        while self.bytes.load(Relaxed) > limit && !ring.slots.is_empty() && visits > 0 {
            visits -= 1;
            let hand = ring.hand % ring.slots.len();
            let slot = &ring.slots[hand];
            if slot.take_referenced() {
                ring.hand = hand + 1;
                continue;
            }
            if slot.evict() {
                ring.slots.swap_remove(hand);
                self.evicted.fetch_add(1, Relaxed);
                ring.hand = hand;
            } else {
                ring.hand = hand + 1;
            }
        }
    }

    /// Drops the ring's empty slots (a level that was dropped emptied its own).
    pub(crate) fn forget_empty(&self) {
        let mut ring = self.ring.lock().unwrap_or_else(|p| p.into_inner());
        ring.slots.retain(|s| !s.is_empty());
        ring.hand = 0;
    }
}

/// Room [`BlockCache::make_room`] made for a block being prepared, given up when dropped
/// (the block prepared, found prepared by another thread, or failed).
pub(crate) struct Room<'a>(&'a BlockCache);

impl Drop for Room<'_> {
    fn drop(&mut self) {
        self.0.preparing.fetch_sub(1, Relaxed);
    }
}

/// A slot of a level: the block prepared there, if any, and its reference bit. Reading is
/// lock-free ([`arc_swap`]); a lock is taken only to prepare a block (so that it is prepared
/// once however many cones want it) and to evict one.
pub(crate) struct Slot<T: Send + Sync> {
    block: arc_swap::ArcSwapOption<T>,
    loading: Mutex<()>,
    referenced: AtomicBool,
    /// The statistics' epoch in which the block was last prepared (0: never), for
    /// [`CacheStats::distinct`].
    prepared: AtomicU64,
}

impl<T: Send + Sync> Default for Slot<T> {
    fn default() -> Self {
        Slot {
            block: arc_swap::ArcSwapOption::empty(),
            loading: Mutex::new(()),
            referenced: AtomicBool::new(false),
            prepared: AtomicU64::new(0),
        }
    }
}

impl<T: Send + Sync + 'static> Slot<T> {
    /// The slot's block, prepared by `load` if it is not there; `Err` from `load` leaves the
    /// slot empty. A block prepared here is handed to `cache` (counted and evictable).
    #[inline]
    pub(crate) fn get_or_load<E>(
        self: &Arc<Self>,
        cache: &BlockCache,
        load: impl FnOnce() -> Result<T, E>,
    ) -> Result<Arc<T>, E> {
        if !self.referenced.load(Relaxed) {
            self.referenced.store(true, Relaxed);
        }
        if let Some(b) = self.block.load_full() {
            return Ok(b);
        }
        self.load_slow(cache, load)
    }

    /// `f` of the slot's block, prepared by `load` if it is not there, without taking a
    /// reference count in the common case (an `arc_swap` guard: a look-up that many threads
    /// make at once, such as a cone's boundary face, does not contend on the block's count).
    #[inline]
    pub(crate) fn with<E, R>(
        self: &Arc<Self>,
        cache: &BlockCache,
        load: impl FnOnce() -> Result<T, E>,
        f: impl FnOnce(&T) -> R,
    ) -> Result<R, E> {
        if !self.referenced.load(Relaxed) {
            self.referenced.store(true, Relaxed);
        }
        {
            let guard = self.block.load();
            if let Some(b) = guard.as_ref() {
                return Ok(f(b));
            }
        }
        Ok(f(&*self.load_slow(cache, load)?))
    }

    #[inline(never)]
    fn load_slow<E>(
        self: &Arc<Self>,
        cache: &BlockCache,
        load: impl FnOnce() -> Result<T, E>,
    ) -> Result<Arc<T>, E> {
        let room = cache.make_room();
        let guard = self.loading.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(b) = self.block.load_full() {
            return Ok(b);
        }
        let b = Arc::new(load()?);
        drop(room);
        self.block.store(Some(b.clone()));
        drop(guard);
        cache.inserted(self.clone(), &self.prepared);
        Ok(b)
    }

    /// Drops the block (a level being dropped).
    pub(crate) fn clear(&self) {
        let _guard = self.loading.lock().unwrap_or_else(|p| p.into_inner());
        self.block.store(None);
    }
}

impl<T: Send + Sync> Evictable for Slot<T> {
    fn take_referenced(&self) -> bool {
        self.referenced.swap(false, Relaxed)
    }
    fn evict(&self) -> bool {
        match self.loading.try_lock() {
            Ok(_guard) => {
                self.block.store(None);
                true
            }
            Err(_) => false,
        }
    }
    fn is_empty(&self) -> bool {
        self.block.load().is_none()
    }
}

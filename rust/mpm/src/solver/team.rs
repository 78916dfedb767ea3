//! A persistent team of worker threads for one frame.
//!
//! A fork-join per stage (rayon's parallel iterators) hands the work to the
//! pool's threads four times per substep; a stage lasts only 5–50 µs for 4k
//! particles, and an idle rayon worker goes to sleep within about that time,
//! so every stage paid a wake-up (measured: p2g after the serial block sort
//! took 38 µs on two threads, 27 µs when its threads were already awake).
//! The team instead takes its threads once per frame (the calling thread is
//! member 0, and one job spawned on the solver's pool per other member) and
//! keeps them for all of its substeps: stages are separated by a spin
//! barrier, items (blocks) are claimed from atomic counters (each member's
//! own range first, [`Team::claim_own`]), and the
//! serial parts run on the last member to arrive while the others wait at
//! the barrier. (`ThreadPool::broadcast`, every member a pool thread, woke
//! one more sleeping thread per frame and left the caller asleep until the
//! pool was done: 30–60 µs of a 0.5 ms frame at 789 particles.)
//!
//! Determinism does not depend on which thread takes which item: every item
//! writes its own output, and the only cross-item combinations (the
//! substep's [`Health`] and largest speed) are maxima, exact in any order.

use std::cell::UnsafeCell;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU32, AtomicUsize, Ordering};
use std::thread::Thread;

use super::Health;

/// Pads a value to its own cache line (no false sharing between counters).
#[repr(align(128))]
pub(super) struct Padded<T>(pub(super) T);

/// A barrier for `n` threads that spins (a stage ends within microseconds),
/// then parks the thread (on a busy machine the thread waited
/// for may not be running: spinning would only keep it off the core). It
/// panics in every waiting thread once the team is poisoned by a panicking
/// member, instead of waiting for it forever.
struct SpinBarrier {
    n: usize,
    arrived: Padded<AtomicUsize>,
    generation: Padded<AtomicUsize>,
    /// Members parked (or about to park) in `wait`.
    sleepers: Padded<AtomicUsize>,
    /// Barriers completed, and waits that ended parked (statistics).
    rounds: AtomicUsize,
    parks: AtomicUsize,
    /// The members' threads, to unpark them.
    threads: Mutex<Vec<Thread>>,
}

/// How long a waiting member spins before it parks: longer than the serial
/// sections and the stages' imbalance on an idle machine (a few to 20 µs for
/// 4k particles), so that a team on free cores never sleeps; a wait longer
/// than that means the member waited for is not running (the machine is
/// busy), and spinning would only keep it off the core.
const SPIN: std::time::Duration = std::time::Duration::from_micros(50);

impl SpinBarrier {
    fn new(n: usize) -> Self {
        SpinBarrier {
            n,
            arrived: Padded(AtomicUsize::new(0)),
            generation: Padded(AtomicUsize::new(0)),
            sleepers: Padded(AtomicUsize::new(0)),
            rounds: AtomicUsize::new(0),
            parks: AtomicUsize::new(0),
            threads: Mutex::new(Vec::with_capacity(n)),
        }
    }

    /// Register the calling thread (once per member, before its first `wait`).
    fn join(&self) {
        self.threads
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(std::thread::current());
    }

    /// Wait until every member has arrived; the last to arrive runs
    /// `serial` first (while all the others wait), so a serial section costs
    /// one barrier instead of two.
    fn wait_then(&self, poisoned: &AtomicBool, serial: impl FnOnce()) {
        if self.n == 1 {
            serial();
            return;
        }
        let generation = self.generation.0.load(Ordering::Acquire);
        // AcqRel: the last to arrive sees everything the others wrote before
        // arriving (their increments form one release sequence)
        if self.arrived.0.fetch_add(1, Ordering::AcqRel) + 1 == self.n {
            serial();
            self.arrived.0.store(0, Ordering::Relaxed);
            self.rounds.fetch_add(1, Ordering::Relaxed);
            self.generation.0.fetch_add(1, Ordering::SeqCst);
            if self.sleepers.0.load(Ordering::SeqCst) > 0 {
                for t in self
                    .threads
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .iter()
                {
                    t.unpark();
                }
            }
            return;
        }
        let mut parked = false;
        let mut spins = 0u32;
        let mut since: Option<std::time::Instant> = None;
        while self.generation.0.load(Ordering::Acquire) == generation {
            if poisoned.load(Ordering::Relaxed) {
                panic!("a thread of the MPM team panicked");
            }
            spins = spins.wrapping_add(1);
            if !spins.is_multiple_of(64) {
                std::hint::spin_loop();
                continue;
            }
            let t0 = *since.get_or_insert_with(std::time::Instant::now);
            if t0.elapsed() < SPIN {
                continue;
            }
            // announce, re-check (the releaser bumps the generation, then
            // reads `sleepers`: one of the two sees the other), park
            parked = true;
            self.sleepers.0.fetch_add(1, Ordering::SeqCst);
            if self.generation.0.load(Ordering::SeqCst) == generation {
                std::thread::park_timeout(std::time::Duration::from_millis(1));
            }
            self.sleepers.0.fetch_sub(1, Ordering::SeqCst);
        }
        if parked {
            self.parks.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// The team's shared state for one frame: the barrier, one work counter per
/// stage, the substep's health and largest speed, the stop flag and a slot
/// for what thread 0 publishes to the others (`V`, written only while the
/// others wait at the barrier).
pub(super) struct Team<V> {
    barrier: SpinBarrier,
    counters: [Padded<AtomicUsize>; 3],
    /// The stages claimed by member ([`Team::claim_own`]): one counter per
    /// (stage, member), `stage * members + member`.
    own: Vec<Padded<AtomicUsize>>,
    health: AtomicU8,
    /// Largest speed squared of the substep, as f32 bits (non-negative
    /// floats order like their bits, so `fetch_max` is the float maximum).
    vmax2: AtomicU32,
    stop: AtomicBool,
    poisoned: AtomicBool,
    shared: UnsafeCell<Option<V>>,
}

// SAFETY: `shared` is written only in serial sections (by the last member
// to arrive at a barrier, while every other member waits) and read by all
// only after that barrier (its Release/Acquire orders the write before the reads).
unsafe impl<V: Send + Sync> Sync for Team<V> {}

/// Stage counters (one each, so a stage's counter can be reset while the
/// previous stage's is still being read).
pub(super) const KEYS: usize = 0;
pub(super) const SORT_COUNT: usize = 1;
pub(super) const SORT_SCATTER: usize = 2;

/// The stages whose items each member claims from its own range first
/// ([`Team::claim_own`]).
pub(super) const OWN_P2G: usize = 0;
pub(super) const OWN_GRID: usize = 1;
pub(super) const OWN_G2P: usize = 2;
const OWN_STAGES: usize = 3;

impl<V: Copy> Team<V> {
    pub(super) fn new(threads: usize) -> Self {
        Team {
            barrier: SpinBarrier::new(threads.max(1)),
            counters: std::array::from_fn(|_| Padded(AtomicUsize::new(0))),
            own: (0..OWN_STAGES * threads.max(1))
                .map(|_| Padded(AtomicUsize::new(0)))
                .collect(),
            health: AtomicU8::new(Health::Ok as u8),
            vmax2: AtomicU32::new(0),
            stop: AtomicBool::new(false),
            poisoned: AtomicBool::new(false),
            shared: UnsafeCell::new(None),
        }
    }

    /// Barriers completed so far, and waits among them that had to park a
    /// member (a sign that the machine has fewer free cores than the team
    /// has threads).
    pub(super) fn barrier_stats(&self) -> (usize, usize) {
        (
            self.barrier.rounds.load(Ordering::Relaxed),
            self.barrier.parks.load(Ordering::Relaxed),
        )
    }

    /// Every member waits here until all have arrived.
    pub(super) fn barrier(&self) {
        self.barrier.wait_then(&self.poisoned, || {});
    }

    /// A barrier whose last member to arrive runs `serial` (the same closure
    /// in every member; one of them runs) before the others go on.
    pub(super) fn barrier_then(&self, serial: impl FnOnce()) {
        self.barrier.wait_then(&self.poisoned, serial);
    }

    /// The next unclaimed item `< n` of stage `stage`, or `None`.
    #[inline]
    pub(super) fn claim(&self, stage: usize, n: usize) -> Option<usize> {
        let i = self.counters[stage].0.fetch_add(1, Ordering::Relaxed);
        (i < n).then_some(i)
    }

    /// The next unclaimed item of stage `stage` (`OWN_*`) for member `tid`,
    /// or `None`: the items `bounds[m] .. bounds[m + 1]` belong to member
    /// `m` (`bounds`: one more entry than the team has members, or `[0, n]`
    /// for all to share one range); a member claims its own items in order,
    /// then helps the others (the next unclaimed item of the next member's
    /// range, and so on). A member so keeps the same particles and grid
    /// blocks from stage to stage and from substep to substep, in its own
    /// core's cache (claimed from one shared counter, about half of them
    /// moved between the cores' caches at every stage), and every item is
    /// still claimed exactly once.
    #[inline]
    pub(super) fn claim_own(&self, stage: usize, tid: usize, bounds: &[u32]) -> Option<usize> {
        let ranges = bounds.len() - 1;
        let members = self.own.len() / OWN_STAGES;
        debug_assert!(ranges == 1 || ranges == members, "one range per member");
        for k in 0..ranges {
            let r = (tid + k) % ranges;
            let (lo, hi) = (bounds[r] as usize, bounds[r + 1] as usize);
            let c = &self.own[stage * members + r].0;
            // (a range seen done is not claimed from again: fewer contended
            // increments at a stage's end)
            if lo + c.load(Ordering::Relaxed) >= hi {
                continue;
            }
            let i = lo + c.fetch_add(1, Ordering::Relaxed);
            if i < hi {
                return Some(i);
            }
        }
        None
    }

    /// Serial section: reset the stage counters, the substep's health and
    /// speed, and publish `v` for the next stages.
    ///
    /// # Safety
    /// Call it only in a serial section (the closure of `barrier_then`),
    /// while every other member waits, or before any member has started.
    pub(super) unsafe fn publish(&self, v: V) {
        for c in self.counters.iter().chain(&self.own) {
            c.0.store(0, Ordering::Relaxed);
        }
        self.health.store(Health::Ok as u8, Ordering::Relaxed);
        self.vmax2.store(0, Ordering::Relaxed);
        // SAFETY: the caller guarantees exclusive access (see above)
        unsafe { *self.shared.get() = Some(v) };
    }

    /// What thread 0 published (after the barrier that follows `publish`).
    ///
    /// # Safety
    /// Call only between the barrier after a `publish` (or, for a `publish`
    /// before any member started, the member's start) and the next serial
    /// section.
    pub(super) unsafe fn published(&self) -> V {
        // SAFETY: no write races with this read (see `publish`)
        unsafe { (*self.shared.get()).expect("published before use") }
    }

    /// Combine one member's health and largest speed squared into the substep's.
    pub(super) fn report(&self, health: Health, vmax2: f32) {
        self.health.fetch_max(health as u8, Ordering::Relaxed);
        // NaN makes health NonFinite, in which case the speed is not used
        self.vmax2
            .fetch_max(vmax2.max(0.0).to_bits(), Ordering::Relaxed);
    }

    /// The substep's health and largest speed (after the barrier that ends g2p).
    pub(super) fn outcome(&self) -> (Health, f32) {
        let h = match self.health.load(Ordering::Relaxed) {
            x if x == Health::Ok as u8 => Health::Ok,
            x if x == Health::Inverted as u8 => Health::Inverted,
            _ => Health::NonFinite,
        };
        (h, f32::from_bits(self.vmax2.load(Ordering::Relaxed)).sqrt())
    }

    /// Serial section: end the frame (seen by all after the barrier).
    pub(super) fn set_stop(&self) {
        self.stop.store(true, Ordering::Relaxed);
    }

    pub(super) fn stopped(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Run `body` as one member (each member calls it once, before its
    /// first `barrier`); a panic poisons the team so that the other
    /// members stop waiting for this one (and panic too).
    pub(super) fn member<R>(&self, body: impl FnOnce() -> R) -> R {
        struct Guard<'a>(&'a AtomicBool);
        impl Drop for Guard<'_> {
            fn drop(&mut self) {
                if std::thread::panicking() {
                    self.0.store(true, Ordering::Relaxed);
                }
            }
        }
        let _guard = Guard(&self.poisoned);
        self.barrier.join();
        body()
    }
}

/// A raw view of a buffer that the team's members write in disjoint chunks.
pub(super) struct RawSlice<T> {
    ptr: *mut T,
    len: usize,
}

impl<T> Clone for RawSlice<T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for RawSlice<T> {}

// SAFETY: members only ever access disjoint chunks of the buffer through
// `chunk_mut` (each chunk belongs to one claimed item), or read it whole
// while nobody writes it (`as_slice`).
unsafe impl<T: Send> Send for RawSlice<T> {}
unsafe impl<T: Send + Sync> Sync for RawSlice<T> {}

impl<T> RawSlice<T> {
    pub(super) fn new(v: &mut [T]) -> Self {
        RawSlice {
            ptr: v.as_mut_ptr(),
            len: v.len(),
        }
    }

    /// Elements `start .. start + len`, exclusively.
    ///
    /// # Safety
    /// No other reference to these elements may exist while the result lives,
    /// and the buffer must not have been reallocated since [`RawSlice::new`].
    #[inline]
    pub(super) unsafe fn chunk_mut<'a>(&self, start: usize, len: usize) -> &'a mut [T] {
        assert!(
            start <= self.len && len <= self.len - start,
            "chunk out of range"
        );
        // SAFETY: in bounds (checked); exclusivity is the caller's promise
        unsafe { std::slice::from_raw_parts_mut(self.ptr.add(start), len) }
    }

    /// Writes `value` at `i`.
    ///
    /// # Safety
    /// No other thread may access element `i` meanwhile, and the buffer must
    /// not have been reallocated since [`RawSlice::new`].
    #[inline]
    pub(super) unsafe fn write(&self, i: usize, value: T) {
        assert!(i < self.len, "index out of range");
        // SAFETY: in bounds (checked); exclusivity is the caller's promise
        unsafe { self.ptr.add(i).write(value) }
    }

    /// A copy of element `i`.
    ///
    /// # Safety
    /// No other thread may write element `i` meanwhile, and the buffer must
    /// not have been reallocated since [`RawSlice::new`].
    #[inline]
    pub(super) unsafe fn read(&self, i: usize) -> T
    where
        T: Copy,
    {
        assert!(i < self.len, "index out of range");
        // SAFETY: in bounds (checked); no concurrent write (caller)
        unsafe { self.ptr.add(i).read() }
    }

    /// Element `i`, exclusively.
    ///
    /// # Safety
    /// As [`RawSlice::chunk_mut`] for the one element.
    #[inline]
    pub(super) unsafe fn get_mut<'a>(&self, i: usize) -> &'a mut T {
        assert!(i < self.len, "index out of range");
        // SAFETY: in bounds (checked); exclusivity is the caller's promise
        unsafe { &mut *self.ptr.add(i) }
    }
}

impl RawSlice<u32> {
    /// The buffer as atomics (same size and alignment as `u32`).
    ///
    /// # Safety
    /// While the result lives every access to the buffer must go through it.
    pub(super) unsafe fn as_atomic<'a>(&self) -> &'a [AtomicU32] {
        // SAFETY: AtomicU32 has the size and alignment of u32 (std docs)
        unsafe { &*std::ptr::slice_from_raw_parts(self.ptr as *const AtomicU32, self.len) }
    }
}

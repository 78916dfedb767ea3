//! The process's rayon pools, one per thread count, shared by the solvers
//! ([`crate::Solver`]) and the Python binding's module functions.
//!
//! Solvers stepped in turn (a hybrid's coarse and fine MPM, a benchmark's
//! pair, several sessions in one server) keep one pool's threads warm: with
//! a pool each, a solver's team found its pool asleep after the other's
//! frames and paid its wake-up every time, enough to make two threads
//! slower than one on small frames (`benchmarks/bench_frame_cost.py turns`,
//! four 2D half grids stepped in turn: two threads' frame 1.14-1.40× one
//! thread's with a pool each, 0.85-1.17× with the shared pool). Sharing is
//! safe: a team's members wait only for each other (the calling thread is
//! member 0, the pool's threads the others), so a frame whose member waits
//! for a pool thread busy with another frame's member is delayed, never
//! deadlocked, and the solver's mode choice sees the delay.
//!
//! rayon's pools do not survive `fork` (PyTorch DataLoader workers,
//! `multiprocessing`): a child would wait forever on threads that do not
//! exist in it. A forked child (another process id than the one that first
//! shared a pool) therefore gets a new pool at every call, and never touches
//! the shared list, whose lock another thread of the parent may have held
//! at the fork; its holders rebuild theirs when the process id changes.

use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, PoisonError, Weak};

use crate::error::{MpmError, Result};

/// The process's pool of `num_threads` threads (`0`: one per core), shared
/// with every other holder that asked for that many; it ends when the last
/// holder drops it. Errors: `InvalidInput` (field `num_threads`) when the
/// pool's threads cannot start.
pub fn shared_pool(num_threads: usize) -> Result<Arc<rayon::ThreadPool>> {
    static SHARING_PID: AtomicU32 = AtomicU32::new(0);
    static POOLS: Mutex<Vec<(usize, Weak<rayon::ThreadPool>)>> = Mutex::new(Vec::new());
    let build = || {
        rayon::ThreadPoolBuilder::new()
            .num_threads(num_threads)
            .build()
            .map(Arc::new)
            .map_err(|e| {
                MpmError::invalid("num_threads", format!("cannot start the thread pool: {e}"))
            })
    };
    let pid = std::process::id();
    match SHARING_PID.compare_exchange(0, pid, Ordering::AcqRel, Ordering::Acquire) {
        Ok(_) => {}
        Err(owner) if owner == pid => {}
        Err(_) => return build(),
    }
    let mut pools = POOLS.lock().unwrap_or_else(PoisonError::into_inner);
    pools.retain(|(_, w)| w.strong_count() > 0);
    if let Some(pool) = pools
        .iter()
        .find(|(n, _)| *n == num_threads)
        .and_then(|(_, w)| w.upgrade())
    {
        return Ok(pool);
    }
    let pool = build()?;
    pools.push((num_threads, Arc::downgrade(&pool)));
    Ok(pool)
}

//! The thread pool of the module-level functions: the process's pool of one
//! thread per core, shared with the solvers that ask for as many
//! ([`hybridmpm_mpm::shared_pool`], which also says why it is fork-safe).
//! rayon's global pool does not survive `fork` (PyTorch DataLoader workers
//! and `multiprocessing` fork), so the module functions never use it; this
//! module holds its pool for the process's life and takes a new one when the
//! process id changes.

use std::sync::{Arc, Mutex};

static POOL: Mutex<Option<(u32, Arc<rayon::ThreadPool>)>> = Mutex::new(None);

fn current() -> Option<Arc<rayon::ThreadPool>> {
    let pid = std::process::id();
    let mut guard = POOL.lock().unwrap_or_else(|e| e.into_inner());
    match &*guard {
        Some((p, pool)) if *p == pid => Some(pool.clone()),
        _ => {
            let pool = hybridmpm_mpm::shared_pool(0).ok()?;
            *guard = Some((pid, pool.clone()));
            Some(pool)
        }
    }
}

/// Run `f` inside the process's pool (or on the calling thread if no pool can start).
pub fn install<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    match current() {
        Some(pool) => pool.install(f),
        None => f(),
    }
}

/// Run the neighbour-crate work `f` on `particles` particles: inside the
/// process's pool where the crate uses rayon for that size
/// (`hybridmpm_neighbors::uses_rayon`), else on the calling thread, which
/// spares the wake-up of a pool worker (15-35 µs on the 2-core machine,
/// as much as the work itself for a few hundred particles).
pub fn install_for<R: Send>(particles: usize, f: impl FnOnce() -> R + Send) -> R {
    if hybridmpm_neighbors::uses_rayon(particles) {
        install(f)
    } else {
        f()
    }
}

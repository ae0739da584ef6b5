//! The scene cache: a source's scene (depth, MPI, masks) is computed once and reused by every
//! sample of that source. Bounded by bytes ([`Scene::byte_size`]), least recently used out.
//!
//! # Behaviour
//!
//! - [`SceneCache::get_or_load`] runs the loader **at most once per key at a time, on every
//!   thread**: a caller that asks for a key another caller is loading waits for that load and
//!   shares its result (counted as a hit, and in [`CacheStats::waits`]). This holds on rayon
//!   worker threads too (every production caller is one): loads run on their own pool
//!   ([`load_pool`], threads named `mpiflow-scene-N`), never nested in the caller's rayon job,
//!   and that pool finishes the load and wakes the waiters itself. A rayon worker that waits
//!   (for the load pool or for another caller's load) may run other jobs of its own pool
//!   meanwhile, and those may wait too, but no load ever waits for the caller's pool, so the
//!   waits always end: no deadlock, no second load. (A loader must not ask the cache for its
//!   own key: it would wait for itself.)
//! - A loaded scene is inserted and the least recently used entries are evicted until the cache
//!   fits in its budget again. A scene larger than the whole budget is returned (also to the
//!   callers waiting for it) but not kept ([`CacheStats::not_kept`]).
//! - **Errors are not cached.** A failed load (or a loader that panics) leaves no entry; callers
//!   that were waiting for it retry the load themselves, one at a time, and a later call retries
//!   too. (A source that fails keeps costing a load attempt per request; the caller sees every
//!   error.)
//! - [`SceneCache::load_absent`] is for builds ahead on the load pool itself (the service's
//!   scene prefetch): it loads a key that is neither cached nor loading, on the calling thread,
//!   and otherwise returns at once; it never waits, so no load-pool thread waits for a load
//!   queued behind it.
//! - The lock is held only for bookkeeping, never while a loader runs, so loads of different
//!   keys proceed in parallel (up to the load pool's size).

use std::collections::HashMap;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};

use super::Scene;

/// What identifies a cached scene: the loader's fingerprint, the source item, and a `variant`
/// word for anything applied to the loaded scene that changes it (e.g. the sample recipe's
/// pre-blend option), so differently prepared scenes of one source never mix.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct SceneKey {
    pub dataset: u64,
    pub item: u64,
    pub variant: u64,
}

impl SceneKey {
    pub fn new(dataset: u64, item: u64, variant: u64) -> Self {
        Self { dataset, item, variant }
    }
}

/// Counters and the current size of a [`SceneCache`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    /// Calls answered without running the loader (including those that waited for a
    /// concurrent load of the same key).
    pub hits: u64,
    /// Calls that ran the loader (successfully or not).
    pub misses: u64,
    /// Of the hits, those that waited for another caller's load.
    pub waits: u64,
    /// Callers waiting now for another caller's load.
    pub waiting: usize,
    /// Entries removed to make room.
    pub evictions: u64,
    /// Loads that failed (returned an error or panicked); never cached.
    pub load_errors: u64,
    /// Loaded scenes larger than the whole budget: returned, not kept.
    pub not_kept: u64,
    /// Scenes held now.
    pub entries: usize,
    /// Bytes held now (sum of [`Scene::byte_size`] of the entries).
    pub bytes: usize,
    /// The budget.
    pub max_bytes: usize,
}

/// The result slot of one load in progress, shared with the threads waiting for it.
#[derive(Default)]
struct Pending {
    /// `None` while loading; `Some(Some(scene))` on success, `Some(None)` on failure.
    done: Mutex<Option<Option<Arc<Scene>>>>,
    cv: Condvar,
}

impl Pending {
    fn finish(&self, result: Option<Arc<Scene>>) {
        *lock(&self.done) = Some(result);
        self.cv.notify_all();
    }

    fn wait(&self) -> Option<Arc<Scene>> {
        let mut g = lock(&self.done);
        loop {
            if let Some(r) = g.as_ref() {
                return r.clone();
            }
            g = self.cv.wait(g).unwrap_or_else(std::sync::PoisonError::into_inner);
        }
    }
}

enum Slot {
    Loading(Arc<Pending>),
    Ready { scene: Arc<Scene>, bytes: usize, last_used: u64 },
}

#[derive(Default)]
struct Inner {
    map: HashMap<SceneKey, Slot>,
    tick: u64,
    bytes: usize,
    stats: CacheStats,
}

/// Called with the seconds of every load the cache ran (successful or not).
pub type LoadObserver = Box<dyn Fn(f64) + Send + Sync>;

/// A byte-bounded, least-recently-used cache of scenes, safe to share between threads.
pub struct SceneCache {
    max_bytes: usize,
    inner: Mutex<Inner>,
    observer: OnceLock<LoadObserver>,
}

impl std::fmt::Debug for SceneCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SceneCache").field("stats", &self.stats()).finish()
    }
}

/// The process-wide pool that runs scene loads (one thread per core, `mpiflow-scene-N`); a
/// model's own threads (ONNX Runtime) come on top. `None` when no thread can be started: loads
/// then run on the caller's thread, which is still correct outside rayon pools.
pub fn load_pool() -> Option<&'static rayon::ThreadPool> {
    static POOL: OnceLock<Option<rayon::ThreadPool>> = OnceLock::new();
    POOL.get_or_init(|| {
        let threads = std::thread::available_parallelism().map_or(1, std::num::NonZeroUsize::get);
        rayon::ThreadPoolBuilder::new().num_threads(threads).thread_name(|i| format!("mpiflow-scene-{i}")).build().ok()
    })
    .as_ref()
}

/// Locks, ignoring poisoning (the cache's invariants are restored by the guards below, and a
/// panic in a loader never happens under the lock).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Removes the `Loading` slot and wakes the waiters if the loader unwinds.
struct LoadGuard<'a> {
    cache: &'a SceneCache,
    key: SceneKey,
    pending: Arc<Pending>,
    armed: bool,
}

impl Drop for LoadGuard<'_> {
    fn drop(&mut self) {
        if self.armed {
            let mut inner = lock(&self.cache.inner);
            inner.stats.load_errors += 1;
            if matches!(inner.map.get(&self.key), Some(Slot::Loading(p)) if Arc::ptr_eq(p, &self.pending)) {
                inner.map.remove(&self.key);
            }
            drop(inner);
            self.pending.finish(None);
        }
    }
}

impl SceneCache {
    /// A cache holding at most `max_bytes` of scenes.
    pub fn new(max_bytes: usize) -> Self {
        Self { max_bytes, inner: Mutex::new(Inner::default()), observer: OnceLock::new() }
    }

    /// Sets the function told the duration of every load (once; later calls are ignored): the
    /// service's `mpiflow_scene_seconds` histogram.
    pub fn observe_loads(&self, observer: LoadObserver) {
        let _ = self.observer.set(observer);
    }

    /// Whether the scene of `key` is cached now (no counter changes, no recency change).
    pub fn contains(&self, key: &SceneKey) -> bool {
        matches!(lock(&self.inner).map.get(key), Some(Slot::Ready { .. }))
    }

    /// Loads in progress now.
    pub fn loading(&self) -> usize {
        lock(&self.inner).map.values().filter(|s| matches!(s, Slot::Loading(_))).count()
    }

    pub fn max_bytes(&self) -> usize {
        self.max_bytes
    }

    /// The scene of `key`: from the cache, from a concurrent load of the same key, or by running
    /// `load` (see the module documentation). Errors of `load` are returned and not cached.
    pub fn get_or_load<E: Send>(
        &self,
        key: SceneKey,
        load: impl FnOnce() -> Result<Scene, E> + Send,
    ) -> Result<Arc<Scene>, E> {
        let mut load = Some(load);
        loop {
            let pending = {
                let mut inner = lock(&self.inner);
                inner.tick += 1;
                let tick = inner.tick;
                match inner.map.get_mut(&key) {
                    Some(Slot::Ready { scene, last_used, .. }) => {
                        *last_used = tick;
                        let scene = scene.clone();
                        inner.stats.hits += 1;
                        return Ok(scene);
                    }
                    Some(Slot::Loading(p)) => {
                        let p = p.clone();
                        inner.stats.waiting += 1;
                        drop(inner);
                        let got = p.wait();
                        let mut inner = lock(&self.inner);
                        inner.stats.waiting -= 1;
                        if let Some(scene) = got {
                            inner.stats.hits += 1;
                            inner.stats.waits += 1;
                            return Ok(scene);
                        }
                        drop(inner);
                        // the load failed: try again (possibly loading it ourselves)
                        continue;
                    }
                    None => {
                        let p = Arc::new(Pending::default());
                        inner.map.insert(key, Slot::Loading(p.clone()));
                        inner.stats.misses += 1;
                        p
                    }
                }
            };
            let f = load.take().expect("the loader runs at most once per call");
            // The load, its insertion and the wake-up of the waiters all run on the load pool:
            // this thread may, while it waits for the pool, run a job of its own pool that waits
            // for this very key, and that wait must end without this thread's help.
            let run = move || self.run_load(key, &pending, f);
            return match load_pool() {
                Some(pool) if pool.current_thread_index().is_none() => pool.install(run),
                _ => run(),
            };
        }
    }

    /// Runs the load of our `Loading` slot here, inserts the scene and wakes the waiters.
    fn run_load<E>(
        &self,
        key: SceneKey,
        pending: &Arc<Pending>,
        f: impl FnOnce() -> Result<Scene, E>,
    ) -> Result<Arc<Scene>, E> {
        let mut guard = LoadGuard { cache: self, key, pending: pending.clone(), armed: true };
        let t = std::time::Instant::now();
        let result = f();
        if let Some(o) = self.observer.get() {
            o(t.elapsed().as_secs_f64());
        }
        match result {
            Ok(scene) => {
                guard.armed = false;
                let scene = Arc::new(scene);
                self.insert(key, pending, scene.clone());
                pending.finish(Some(scene.clone()));
                Ok(scene)
            }
            // the guard removes the slot, counts the error and wakes the waiters
            Err(e) => Err(e),
        }
    }

    /// Loads the scene of `key` on this thread when it is neither cached nor being loaded (a
    /// miss, as [`get_or_load`](Self::get_or_load) counts it); returns at once, without
    /// waiting and without running `load`, when it is. For builds ahead on the load pool, whose
    /// threads must never wait for a load queued behind them. Errors are not cached.
    pub fn load_absent<E>(
        &self,
        key: SceneKey,
        load: impl FnOnce() -> Result<Scene, E>,
    ) -> Option<Result<Arc<Scene>, E>> {
        let pending = {
            let mut inner = lock(&self.inner);
            if inner.map.contains_key(&key) {
                return None;
            }
            let p = Arc::new(Pending::default());
            inner.map.insert(key, Slot::Loading(p.clone()));
            inner.stats.misses += 1;
            p
        };
        Some(self.run_load(key, &pending, load))
    }

    /// Replaces our `Loading` slot by the scene (or drops it when the scene is over budget) and
    /// evicts least recently used entries until the budget holds.
    fn insert(&self, key: SceneKey, pending: &Arc<Pending>, scene: Arc<Scene>) {
        let bytes = scene.byte_size();
        let mut inner = lock(&self.inner);
        if matches!(inner.map.get(&key), Some(Slot::Loading(p)) if Arc::ptr_eq(p, pending)) {
            inner.map.remove(&key);
        }
        if bytes > self.max_bytes {
            inner.stats.not_kept += 1;
            return;
        }
        inner.tick += 1;
        let tick = inner.tick;
        inner.map.insert(key, Slot::Ready { scene, bytes, last_used: tick });
        inner.bytes += bytes;
        while inner.bytes > self.max_bytes {
            let victim = inner
                .map
                .iter()
                .filter_map(|(k, s)| match s {
                    Slot::Ready { last_used, .. } if *k != key => Some((*last_used, *k)),
                    _ => None,
                })
                .min();
            let Some((_, victim)) = victim else { break };
            if let Some(Slot::Ready { bytes, .. }) = inner.map.remove(&victim) {
                inner.bytes -= bytes;
                inner.stats.evictions += 1;
            }
        }
    }

    /// The cached scene of `key`, if present (counts as a hit and refreshes its recency; a miss
    /// is not counted since nothing is loaded).
    pub fn get(&self, key: &SceneKey) -> Option<Arc<Scene>> {
        let mut inner = lock(&self.inner);
        inner.tick += 1;
        let tick = inner.tick;
        match inner.map.get_mut(key) {
            Some(Slot::Ready { scene, last_used, .. }) => {
                *last_used = tick;
                let s = scene.clone();
                inner.stats.hits += 1;
                Some(s)
            }
            _ => None,
        }
    }

    /// Drops every cached scene (loads in progress finish normally and are inserted).
    pub fn clear(&self) {
        let mut inner = lock(&self.inner);
        inner.map.retain(|_, s| matches!(s, Slot::Loading(_)));
        inner.bytes = 0;
    }

    /// Counters and the current size.
    pub fn stats(&self) -> CacheStats {
        let inner = lock(&self.inner);
        let entries = inner.map.values().filter(|s| matches!(s, Slot::Ready { .. })).count();
        CacheStats { entries, bytes: inner.bytes, max_bytes: self.max_bytes, ..inner.stats }
    }
}

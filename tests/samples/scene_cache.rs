//! The scene cache: computed once per key (also under concurrent requests), bounded by bytes with
//! least-recently-used eviction, oversize scenes returned but not kept, errors not cached.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Barrier};

use std::time::Duration;

use mpiflow::geometry::Intrinsics;
use mpiflow::io::image::RgbImage;
use mpiflow::mpi::Mpi;
use mpiflow::raster::InstanceMasks;
use mpiflow::scene::cache::{SceneCache, SceneKey};
use mpiflow::scene::{Disparity, Scene};

/// A scene of `w` x `h` pixels and `planes` planes (its byte size grows with both).
fn scene(id: &str, w: usize, h: usize, planes: usize) -> Scene {
    let disp: Vec<f64> = (0..planes).map(|i| 1.0 - i as f64 / (planes as f64 + 1.0)).collect();
    Scene {
        id: id.to_string(),
        image: RgbImage { width: w, height: h, data: vec![0.5; w * h * 3] },
        disparity: Disparity { width: w, height: h, data: vec![0.5; w * h] },
        mpi: Arc::new(Mpi::new(w, h, disp, 0)),
        masks: InstanceMasks::new(w, h),
        intrinsics: Intrinsics::reference_default(w, h),
        provenance: vec!["test".into()],
    }
}

fn key(item: u64) -> SceneKey {
    SceneKey::new(7, item, 0)
}

type Never = std::convert::Infallible;

#[test]
fn second_request_is_a_hit_and_shares_the_scene() {
    let cache = SceneCache::new(1 << 30);
    let calls = AtomicUsize::new(0);
    let load = || -> Result<Scene, Never> {
        calls.fetch_add(1, Ordering::SeqCst);
        Ok(scene("a", 16, 8, 2))
    };
    let a = cache.get_or_load(key(0), load).unwrap();
    let b = cache.get_or_load(key(0), load).unwrap();
    assert!(Arc::ptr_eq(&a, &b));
    assert_eq!(calls.load(Ordering::SeqCst), 1);
    let s = cache.stats();
    assert_eq!((s.hits, s.misses, s.entries, s.evictions), (1, 1, 1, 0));
    assert_eq!(s.bytes, a.byte_size());
    // another variant of the same item is another scene
    let c = cache.get_or_load(SceneKey::new(7, 0, 1), load).unwrap();
    assert!(!Arc::ptr_eq(&a, &c));
    assert_eq!(cache.stats().misses, 2);
}

/// Waits (bounded) until `n` callers wait for a load in progress: the observable state that
/// proves the requests are concurrent.
fn wait_for_waiters(cache: &SceneCache, n: usize) {
    let t = std::time::Instant::now();
    while cache.stats().waiting < n {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "only {} of {n} callers waited: {:?}",
            cache.stats().waiting,
            cache.stats()
        );
        std::thread::yield_now();
    }
}

/// Production's shape: every request is a job on a rayon pool (the service's worker pool), and
/// the load itself runs parallel loops. 8 concurrent jobs for one key run the loader once; the
/// loader is held until the 7 others are seen waiting, so the requests provably overlap.
#[test]
fn concurrent_requests_on_a_rayon_pool_load_once() {
    let threads = 8;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
    let cache = Arc::new(SceneCache::new(1 << 30));
    let calls = Arc::new(AtomicUsize::new(0));
    let (release_tx, release_rx) = std::sync::mpsc::channel::<()>();
    let release_rx = std::sync::Mutex::new(release_rx);
    let scenes: Vec<Arc<Scene>> = std::thread::scope(|scope| {
        let main = scope.spawn(|| {
            pool.install(|| {
                use rayon::prelude::*;
                (0..threads)
                    .into_par_iter()
                    .map(|_| {
                        cache
                            .get_or_load(key(3), || -> Result<Scene, Never> {
                                calls.fetch_add(1, Ordering::SeqCst);
                                let _ = release_rx.lock().unwrap().recv_timeout(Duration::from_secs(60));
                                // a parallel loop inside the load, as the layering and models run
                                let sum: u64 = (0..10_000u64).into_par_iter().map(|i| i % 7).sum();
                                assert!(sum > 0);
                                Ok(scene("slow", 32, 16, 4))
                            })
                            .unwrap()
                    })
                    .collect::<Vec<_>>()
            })
        });
        wait_for_waiters(&cache, threads - 1);
        release_tx.send(()).unwrap();
        main.join().unwrap()
    });
    assert_eq!(calls.load(Ordering::SeqCst), 1, "the loader ran more than once");
    assert!(scenes.iter().all(|s| Arc::ptr_eq(s, &scenes[0])));
    let s = cache.stats();
    assert_eq!(s.misses, 1);
    assert_eq!(s.hits, threads as u64 - 1);
    assert_eq!(s.waits, threads as u64 - 1, "{s:?}");
    assert_eq!(s.waiting, 0);
}

/// A worker pool smaller than the number of requests: a worker that waits for the load pool may
/// run other jobs of its own pool, which then wait for the same load; the waits end because the
/// load pool finishes the load and wakes the waiters itself. 2 workers, 32 jobs over 4 keys,
/// loaders with parallel loops: each key loaded once, no deadlock.
#[test]
fn a_small_worker_pool_with_many_jobs_per_key_neither_deadlocks_nor_loads_twice() {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    let cache = Arc::new(SceneCache::new(1 << 30));
    let calls: Arc<Vec<AtomicUsize>> = Arc::new((0..4).map(|_| AtomicUsize::new(0)).collect());
    let (tx, rx) = std::sync::mpsc::channel();
    {
        let (cache, calls) = (cache.clone(), calls.clone());
        pool.spawn(move || {
            use rayon::prelude::*;
            let ids: Vec<String> = (0..32u64)
                .into_par_iter()
                .map(|j| {
                    let k = j % 4;
                    cache
                        .get_or_load(key(100 + k), || -> Result<Scene, Never> {
                            calls[k as usize].fetch_add(1, Ordering::SeqCst);
                            let sum: u64 = (0..50_000u64).into_par_iter().map(|i| i % 3).sum();
                            assert!(sum > 0);
                            Ok(scene(&format!("k{k}"), 16, 16, 2))
                        })
                        .unwrap()
                        .id
                        .clone()
                })
                .collect();
            tx.send(ids).unwrap();
        });
    }
    let ids = rx.recv_timeout(Duration::from_secs(60)).expect("no deadlock");
    for (j, id) in ids.iter().enumerate() {
        assert_eq!(*id, format!("k{}", j % 4));
    }
    for (k, c) in calls.iter().enumerate() {
        assert_eq!(c.load(Ordering::SeqCst), 1, "key {k} loaded more than once");
    }
}

#[test]
fn least_recently_used_is_evicted_within_the_byte_budget() {
    let one = scene("x", 32, 32, 4).byte_size();
    let cache = SceneCache::new(2 * one + one / 2);
    let get = |i: u64| cache.get_or_load(key(i), || -> Result<Scene, Never> { Ok(scene(&format!("s{i}"), 32, 32, 4)) });
    get(0).unwrap();
    get(1).unwrap();
    get(0).unwrap(); // 0 is now more recent than 1
    get(2).unwrap(); // evicts 1
    let s = cache.stats();
    assert_eq!((s.entries, s.evictions), (2, 1));
    assert!(s.bytes <= s.max_bytes);
    assert!(cache.get(&key(0)).is_some());
    assert!(cache.get(&key(2)).is_some());
    assert!(cache.get(&key(1)).is_none());
    // reloading 1 evicts the least recently used of {0, 2}: 0 (2 was touched last)
    get(1).unwrap();
    assert!(cache.get(&key(0)).is_none());
    assert_eq!(cache.stats().evictions, 2);
    assert_eq!(cache.stats().misses, 4);
}

#[test]
fn a_scene_larger_than_the_budget_is_returned_but_not_kept() {
    let big = scene("big", 64, 64, 8);
    let cache = SceneCache::new(big.byte_size() - 1);
    let small = cache.get_or_load(key(1), || -> Result<Scene, Never> { Ok(scene("small", 8, 8, 1)) }).unwrap();
    let got = cache.get_or_load(key(0), || -> Result<Scene, Never> { Ok(big) }).unwrap();
    assert_eq!(got.id, "big");
    let s = cache.stats();
    assert_eq!((s.entries, s.not_kept, s.evictions), (1, 1, 0), "the small scene stays: {s:?}");
    assert_eq!(s.bytes, small.byte_size());
}

#[test]
fn errors_are_not_cached() {
    let cache = SceneCache::new(1 << 30);
    let r: Result<_, String> = cache.get_or_load(key(5), || Err("disk on fire".to_string()));
    assert_eq!(r.unwrap_err(), "disk on fire");
    let s = cache.stats();
    assert_eq!((s.entries, s.load_errors, s.misses), (0, 1, 1));
    let ok = cache.get_or_load(key(5), || -> Result<Scene, String> { Ok(scene("ok", 8, 8, 1)) }).unwrap();
    assert_eq!(ok.id, "ok");
    assert_eq!(cache.stats().misses, 2);
}

#[test]
fn waiters_retry_after_a_failed_load_and_a_panicking_loader_blocks_nobody() {
    let cache = Arc::new(SceneCache::new(1 << 30));
    let calls = Arc::new(AtomicUsize::new(0));
    let threads = 4;
    let barrier = Arc::new(Barrier::new(threads));
    let handles: Vec<_> = (0..threads)
        .map(|_| {
            let (cache, calls, barrier) = (cache.clone(), calls.clone(), barrier.clone());
            std::thread::spawn(move || {
                barrier.wait();
                cache.get_or_load(key(9), || {
                    let n = calls.fetch_add(1, Ordering::SeqCst);
                    std::thread::sleep(Duration::from_millis(50));
                    if n == 0 {
                        Err("first attempt fails")
                    } else {
                        Ok(scene("second", 8, 8, 1))
                    }
                })
            })
        })
        .collect();
    let results: Vec<_> = handles.into_iter().map(|h| h.join().unwrap()).collect();
    assert_eq!(results.iter().filter(|r| r.is_err()).count(), 1, "only the failing loader sees its error");
    assert_eq!(calls.load(Ordering::SeqCst), 2, "one failed load, then one successful retry shared by the rest");

    // a loader that panics leaves no entry behind and wakes nobody up wrongly
    let c2 = cache.clone();
    let panicked = std::thread::spawn(move || {
        c2.get_or_load(key(10), || -> Result<Scene, Never> { panic!("loader bug") }).ok();
    })
    .join();
    assert!(panicked.is_err());
    let after = cache.get_or_load(key(10), || -> Result<Scene, Never> { Ok(scene("fine", 8, 8, 1)) }).unwrap();
    assert_eq!(after.id, "fine");
    assert_eq!(cache.stats().load_errors, 2);
}

#[test]
fn clear_drops_everything() {
    let cache = SceneCache::new(1 << 30);
    for i in 0..3 {
        cache.get_or_load(key(i), || -> Result<Scene, Never> { Ok(scene("s", 8, 8, 1)) }).unwrap();
    }
    assert_eq!(cache.stats().entries, 3);
    cache.clear();
    let s = cache.stats();
    assert_eq!((s.entries, s.bytes), (0, 0));
}

//! The server's epoch run from inside rayon's pool with every pool thread busy, as `fleet
//! experiment` runs its rows: the epoch's own parallel loops (the filter's per-cell passes, the
//! placement beside the model) must not wait for a pool thread that is waiting for them. A
//! binary of its own, so that rayon's global pool can be one thread (always busy).

/// A grid large enough for the epoch's loops to go parallel (192 x 384): it hung before the
/// model was made with `rayon::join` rather than on a thread the pool's thread joined.
#[test]
fn epochs_inside_a_busy_rayon_pool_complete() {
    use fleet::experiment::epoch_timing::{run, Fleet};
    rayon::ThreadPoolBuilder::new().num_threads(1).build_global().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let fleet = Fleet {
            aerials: 2,
            boats: 5,
            radius: 8.0,
        };
        // The run on the pool's one thread, as `fleet experiment`'s rows are.
        let (timing, _) = rayon::join(|| run(192, 384, fleet, 3).map(|t| t.epochs), || ());
        tx.send(timing).unwrap();
    });
    let done = rx
        .recv_timeout(std::time::Duration::from_secs(120))
        .expect("the epochs did not complete in 120 s: the pool's thread waits for work only the pool can do");
    assert!(done.unwrap() >= 2);
}

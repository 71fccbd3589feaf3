//! Two pieces of work side by side on rayon's pool: the model server's epoch runs what needs
//! nothing of the other together (the filter's step and the next step's aerial sight, the
//! refit's modes and its basis, the placement and the published model).

/// `a` and `b` side by side on rayon's pool, both with this thread's `tracing` subscriber (the
/// bench's phases): a join called from outside the pool runs both closures on its threads.
/// Not a thread of its own that this one joins: inside `fleet experiment`'s parallel rows this
/// thread is one of the pool's, and a pool thread blocked on a join cannot run the closures'
/// own parallel loops.
pub fn beside<A: Send, B: Send>(a: impl FnOnce() -> A + Send, b: impl FnOnce() -> B + Send) -> (A, B) {
    let dispatch = tracing::dispatcher::get_default(|d| d.clone());
    rayon::join(
        || tracing::dispatcher::with_default(&dispatch, a),
        || tracing::dispatcher::with_default(&dispatch, b),
    )
}

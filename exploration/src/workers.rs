//! The threads a replanning may use, and the hook that can hold them back.
//!
//! A replanning spreads its searches over a few threads ([`in_parallel`]).
//! The caller may want those threads to stop now and then: an executive
//! under a CPU limit (a container's quota) must not let one plan spend the
//! quota that its requests need in the same period. This module knows
//! nothing of time or CPU; it only tells the caller's [`Pace`] each time a
//! thread has finished a piece of work, on that thread, where it may wait.

use std::fmt::Debug;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Told on a worker thread each time it has finished one piece of a
/// replanning's parallel work; it may block the thread there for as long
/// as it likes. The plan is the same whatever it does.
pub trait Pace: Sync + Debug {
    /// The calling thread has finished a piece of work.
    fn piece_done(&self);
}

/// Never holds a thread back.
#[derive(Debug, Clone, Copy, Default)]
pub struct Unpaced;

impl Pace for Unpaced {
    #[inline]
    fn piece_done(&self) {}
}

/// How many threads a replanning may use, and what paces them.
#[derive(Debug, Clone, Copy)]
pub struct Workers<'a> {
    /// Threads, at least one.
    pub threads: usize,
    /// Told after each piece of work.
    pub pace: &'a dyn Pace,
}

impl Workers<'static> {
    /// `threads` threads, never held back.
    pub fn unpaced(threads: usize) -> Self {
        Self { threads, pace: &Unpaced }
    }
}

/// `f` over `items` on up to `workers.threads` scoped threads, results in
/// order; each thread tells the pace after each item.
///
/// Thread k starts with item k and then takes the next item nobody has
/// taken, so items start in order (`unassigned`'s searches tell each robot
/// what the robots before it chose, and need those searched first), and
/// no thread idles behind another's long share (searches differ in size by
/// orders of magnitude: a robot beside a frontier against one across the
/// building).
pub fn in_parallel<T: Sync, R: Send>(items: &[T], workers: Workers<'_>, f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let threads = workers.threads.clamp(1, items.len().max(1));
    let paced = |item: &T| {
        let result = f(item);
        workers.pace.piece_done();
        result
    };
    if threads == 1 {
        return items.iter().map(paced).collect();
    }
    let next = AtomicUsize::new(threads);
    let done: Vec<(usize, R)> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..threads)
            .map(|first| {
                let (next, paced) = (&next, &paced);
                scope.spawn(move || {
                    let mut done = Vec::new();
                    let mut i = first;
                    while let Some(item) = items.get(i) {
                        done.push((i, paced(item)));
                        i = next.fetch_add(1, Ordering::Relaxed);
                    }
                    done
                })
            })
            .collect();
        handles.into_iter().flat_map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))).collect()
    });
    let mut slots: Vec<Option<R>> = std::iter::repeat_with(|| None).take(items.len()).collect();
    for (i, r) in done {
        slots[i] = Some(r);
    }
    slots.into_iter().flatten().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;
    use std::sync::Mutex;
    use std::thread::ThreadId;

    /// Counts the pieces each thread reports.
    #[derive(Debug, Default)]
    struct Tally(Mutex<HashMap<ThreadId, usize>>);

    impl Pace for Tally {
        fn piece_done(&self) {
            *self.0.lock().unwrap().entry(std::thread::current().id()).or_default() += 1;
        }
    }

    #[test]
    fn every_piece_is_told_on_the_thread_that_did_it() {
        for threads in [1, 2, 3, 8] {
            let tally = Tally::default();
            let items: Vec<u32> = (0..7).collect();
            let doubled =
                in_parallel(&items, Workers { threads, pace: &tally }, |&x| (x * 2, std::thread::current().id()));
            assert_eq!(doubled.iter().map(|(x, _)| *x).collect::<Vec<_>>(), vec![0, 2, 4, 6, 8, 10, 12]);
            let mut by_worker: HashMap<ThreadId, usize> = HashMap::new();
            for (_, id) in &doubled {
                *by_worker.entry(*id).or_default() += 1;
            }
            assert_eq!(*tally.0.lock().unwrap(), by_worker, "{threads} threads");
            assert_eq!(by_worker.len(), threads.min(7), "{threads} threads");
        }
    }

    /// A long item does not hold back the items after it: while the
    /// first waits for every other item to be done, the second thread does
    /// them all (with fixed shares, the first thread's share would wait
    /// behind it for ever).
    #[test]
    fn an_idle_thread_takes_the_next_item() {
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        let rx = Mutex::new(rx);
        let items: Vec<u32> = (0..9).collect();
        let out = in_parallel(&items, Workers::unpaced(2), |&x| {
            if x == 0 {
                let rx = rx.lock().unwrap();
                for _ in 1..9 {
                    // A guard against hanging, not a measure: the others take microseconds.
                    rx.recv_timeout(std::time::Duration::from_secs(30)).expect("the other items were done meanwhile");
                }
            } else {
                tx.send(()).unwrap();
            }
            x + 1
        });
        assert_eq!(out, (1..10).collect::<Vec<_>>());
    }

    #[test]
    fn nothing_to_do_tells_nothing() {
        let tally = Tally::default();
        let none: Vec<u32> = in_parallel(&[], Workers { threads: 4, pace: &tally }, |&x: &u32| x);
        assert!(none.is_empty());
        assert!(tally.0.lock().unwrap().is_empty());
    }
}

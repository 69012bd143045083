//! The bounded queue between the DDS receive loop and the worker thread.
//!
//! Drop policy: when the queue is full, the OLDEST waiting item is dropped (and counted) to make room
//! for the new one. A loop detector wants the newest keyframes: an old keyframe that waited behind a
//! slow inference is the least useful one, and the receive loop must never block (blocking it would
//! back-pressure DDS and stall parameter traffic). Control messages (parameter changes) travel in a
//! separate lane that is never dropped and is served before the next item.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex};
use std::time::Duration;

/// What the worker takes next.
#[derive(Debug, PartialEq)]
pub enum Next<T, C> {
    Control(C),
    Item(T),
    /// The queue was closed and is empty.
    Closed,
    /// Nothing arrived within the wait.
    Timeout,
}

struct State<T, C> {
    items: VecDeque<T>,
    control: VecDeque<C>,
    closed: bool,
    dropped: u64,
}

/// A multi-producer, single-consumer queue of capacity `capacity` with drop-oldest overflow.
pub struct DropOldestQueue<T, C> {
    capacity: usize,
    state: Mutex<State<T, C>>,
    ready: Condvar,
}

impl<T, C> DropOldestQueue<T, C> {
    /// `capacity` is at least 1.
    pub fn new(capacity: usize) -> Self {
        DropOldestQueue {
            capacity: capacity.max(1),
            state: Mutex::new(State { items: VecDeque::new(), control: VecDeque::new(), closed: false, dropped: 0 }),
            ready: Condvar::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State<T, C>> {
        // A panic elsewhere while holding the lock leaves the queue's data consistent (plain pushes and
        // pops), so carry on rather than propagate the poison.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Adds an item; returns the dropped oldest one if the queue was full.
    pub fn push(&self, item: T) -> Option<T> {
        let mut state = self.lock();
        let dropped = if state.items.len() >= self.capacity {
            state.dropped += 1;
            state.items.pop_front()
        } else {
            None
        };
        state.items.push_back(item);
        drop(state);
        self.ready.notify_one();
        dropped
    }

    /// Adds a control message (never dropped, served before items).
    pub fn push_control(&self, control: C) {
        self.lock().control.push_back(control);
        self.ready.notify_one();
    }

    /// No more items: the consumer drains what is left, then gets [`Next::Closed`].
    pub fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }

    /// Items dropped so far.
    pub fn dropped(&self) -> u64 {
        self.lock().dropped
    }

    pub fn len(&self) -> usize {
        self.lock().items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Waits up to `timeout` for the next control message or item.
    pub fn pop(&self, timeout: Duration) -> Next<T, C> {
        let mut state = self.lock();
        let deadline = std::time::Instant::now() + timeout;
        loop {
            if let Some(c) = state.control.pop_front() {
                return Next::Control(c);
            }
            if let Some(item) = state.items.pop_front() {
                return Next::Item(item);
            }
            if state.closed {
                return Next::Closed;
            }
            let now = std::time::Instant::now();
            if now >= deadline {
                return Next::Timeout;
            }
            state = self.ready.wait_timeout(state, deadline - now).unwrap_or_else(|e| e.into_inner()).0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn drops_the_oldest_and_counts() {
        let q: DropOldestQueue<u32, &str> = DropOldestQueue::new(2);
        assert_eq!(q.push(1), None);
        assert_eq!(q.push(2), None);
        assert_eq!(q.push(3), Some(1));
        assert_eq!(q.push(4), Some(2));
        assert_eq!(q.dropped(), 2);
        q.push_control("threshold");
        assert_eq!(q.pop(Duration::ZERO), Next::Control("threshold"));
        assert_eq!(q.pop(Duration::ZERO), Next::Item(3));
        assert_eq!(q.pop(Duration::ZERO), Next::Item(4));
        assert_eq!(q.pop(Duration::from_millis(5)), Next::Timeout);
        q.close();
        assert_eq!(q.pop(Duration::from_secs(5)), Next::Closed);
    }

    #[test]
    fn consumer_wakes_on_push_from_another_thread() {
        let q: Arc<DropOldestQueue<u32, ()>> = Arc::new(DropOldestQueue::new(4));
        let producer = {
            let q = q.clone();
            std::thread::spawn(move || {
                for i in 0..100 {
                    q.push(i);
                }
                q.close();
            })
        };
        let mut got = Vec::new();
        loop {
            match q.pop(Duration::from_secs(5)) {
                Next::Item(i) => got.push(i),
                Next::Closed => break,
                Next::Timeout => panic!("consumer starved"),
                Next::Control(()) => unreachable!(),
            }
        }
        producer.join().unwrap();
        // Whatever was dropped, what arrived is in order and ends with the last item.
        assert!(got.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(*got.last().unwrap(), 99);
        assert_eq!(got.len() as u64 + q.dropped(), 100);
    }
}

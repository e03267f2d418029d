//! Handing a parallel pass's units to a consumer in unit order, whichever thread finished them.

use std::collections::BTreeMap;
use std::sync::{Mutex, TryLockError};

/// The units finished but not yet consumed, and the consumer: the next unit's number and
/// `consume`, behind a lock of their own, so that a thread finding the consumer busy goes back to
/// its work instead of waiting while another thread consumes. An optimisation step's passes are
/// small (64 units of a few dozen pixels each), and waiting for the lock there made a step 8 %
/// longer on 2 threads.
pub struct InOrder<T, C> {
    finished: Mutex<BTreeMap<u64, T>>,
    consumer: Mutex<(u64, C)>,
}

impl<T, C: FnMut(T)> InOrder<T, C> {
    pub fn new(consume: C) -> Self {
        InOrder {
            finished: Mutex::new(BTreeMap::new()),
            consumer: Mutex::new((0, consume)),
        }
    }

    /// Unit `unit` is done: it is consumed with every finished unit after it in order, by this
    /// thread unless another one is consuming already.
    pub fn finish(&self, unit: u64, acc: T) {
        (self.finished.lock().expect("no unit panicked")).insert(unit, acc);
        self.consume_ready(false);
    }

    /// Consumes what `finish` left behind; call once every unit is finished. (A unit finished
    /// while another thread was consuming, just after it looked for that unit, stays behind.)
    pub fn consume_rest(&self) {
        self.consume_ready(true);
    }

    fn consume_ready(&self, wait: bool) {
        let mut consumer = match self.consumer.try_lock() {
            Ok(consumer) => consumer,
            Err(TryLockError::WouldBlock) if !wait => return,
            Err(_) => self.consumer.lock().expect("no unit panicked"),
        };
        let (next, consume) = &mut *consumer;
        loop {
            let unit = self.finished.lock().expect("no unit panicked").remove(next);
            let Some(acc) = unit else { break };
            consume(acc);
            *next += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    #[test]
    fn units_finished_in_any_order_on_any_thread_are_consumed_in_order() {
        let mut seen = Vec::new();
        {
            let in_order = InOrder::new(|unit: u64| seen.push(unit));
            // Units finished out of order, from several threads at once.
            (0..1000u64)
                .into_par_iter()
                .map(|i| (i * 7919) % 1000)
                .for_each(|unit| in_order.finish(unit, unit));
            in_order.consume_rest();
        }
        assert_eq!(seen, (0..1000).collect::<Vec<_>>());
    }

    #[test]
    fn a_unit_finished_while_another_thread_consumes_is_consumed_at_the_end() {
        let mut seen = Vec::new();
        {
            let in_order = InOrder::new(|unit: u64| seen.push(unit));
            in_order.finish(0, 0);
            {
                // Another thread holds the consumer: unit 1 must be left, not waited for.
                let _busy = in_order.consumer.lock().unwrap();
                in_order.finish(1, 1);
            }
            in_order.consume_rest();
        }
        assert_eq!(seen, [0, 1]);
    }
}

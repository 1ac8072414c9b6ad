//! The queue from the links to the service, bounded in frames and samples however the links group
//! them into items.
//!
//! A live link queues what one read gave as one item ([`Inbound::Frames`]): one hand-over per read
//! instead of one per frame. The bound stays the service's `daemon.queue_capacity` frames (and
//! samples, and status changes, one each): an item takes that much room from a semaphore when it is
//! queued and gives it back when the service drops it, after handling it. A live link that finds no
//! room drops the whole item and counts each of its frames; a replay waits for room.

use super::Inbound;
use std::sync::Arc;
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};

/// Frames per item at most: a read that gives more is queued as several items, so that an item
/// never needs more room than the queue has, and a dropped item loses a bounded run of frames.
pub(crate) const FRAMES_PER_ITEM: usize = 128;

/// An item on the queue, with the room it takes (given back when the item is dropped).
#[derive(Debug)]
pub(crate) struct Queued {
    pub item: Inbound,
    room: OwnedSemaphorePermit,
}

impl Queued {
    /// The item; its room is given back when `self` is dropped (the caller keeps it until the item
    /// is handled).
    pub fn into_parts(self) -> (Inbound, OwnedSemaphorePermit) {
        (self.item, self.room)
    }
}

/// Why an item was not queued.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Refused {
    /// No room: the item is dropped (its frames counted by the caller).
    Full,
    /// The service is gone.
    Closed,
}

/// The links' end of the queue (one clone per link).
#[derive(Debug, Clone)]
pub(crate) struct InboundTx {
    /// Unbounded as a channel: `room` bounds it, since every item takes at least one unit.
    items: mpsc::UnboundedSender<Queued>,
    room: Arc<Semaphore>,
    capacity: usize,
}

/// The service's end of the queue.
#[derive(Debug)]
pub(crate) struct InboundRx {
    items: mpsc::UnboundedReceiver<Queued>,
}

/// A queue for `capacity` frames and samples (at least 1).
pub(crate) fn inbound_queue(capacity: usize) -> (InboundTx, InboundRx) {
    let capacity = capacity.clamp(1, Semaphore::MAX_PERMITS.min(u32::MAX as usize));
    let (tx, rx) = mpsc::unbounded_channel();
    (
        InboundTx {
            items: tx,
            room: Arc::new(Semaphore::new(capacity)),
            capacity,
        },
        InboundRx { items: rx },
    )
}

impl InboundTx {
    /// The most frames one item may hold: [`FRAMES_PER_ITEM`], or fewer when the queue is smaller.
    pub fn max_batch(&self) -> usize {
        FRAMES_PER_ITEM.min(self.capacity)
    }

    /// The room an item takes (at most the queue's capacity, so a replay's wait always ends).
    fn units(&self, item: &Inbound) -> u32 {
        let n = match item {
            Inbound::Frames { frames, .. } => frames.len().max(1),
            Inbound::Sample { .. } | Inbound::Status { .. } => 1,
        };
        // (`capacity` fits a u32: see `inbound_queue`.)
        n.min(self.capacity) as u32
    }

    /// Queue without waiting (live links).
    pub fn try_send(&self, item: Inbound) -> Result<(), Refused> {
        let room = match self.room.clone().try_acquire_many_owned(self.units(&item)) {
            Ok(r) => r,
            Err(tokio::sync::TryAcquireError::NoPermits) => return Err(Refused::Full),
            Err(tokio::sync::TryAcquireError::Closed) => return Err(Refused::Closed),
        };
        self.items
            .send(Queued { item, room })
            .map_err(|_| Refused::Closed)
    }

    /// Queue, waiting for room (replays). `Err` when the service is gone.
    pub async fn send(&self, item: Inbound) -> Result<(), Refused> {
        let room = self
            .room
            .clone()
            .acquire_many_owned(self.units(&item))
            .await
            .map_err(|_| Refused::Closed)?;
        if self.items.is_closed() {
            return Err(Refused::Closed);
        }
        self.items
            .send(Queued { item, room })
            .map_err(|_| Refused::Closed)
    }
}

impl InboundRx {
    /// Wait for items and take up to `limit` of them; 0 when every link's end is gone.
    pub async fn recv_many(&mut self, buf: &mut Vec<Queued>, limit: usize) -> usize {
        self.items.recv_many(buf, limit).await
    }

    /// The next item; `None` when every link's end is gone.
    #[cfg(test)]
    pub async fn recv(&mut self) -> Option<Queued> {
        self.items.recv().await
    }

    /// An item if one is queued.
    pub fn try_recv(&mut self) -> Option<Queued> {
        self.items.try_recv().ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::link::LinkStatus;

    fn status() -> Inbound {
        Inbound::Status {
            link: 0,
            status: LinkStatus::Ended,
        }
    }

    #[tokio::test]
    async fn room_is_counted_per_unit_and_given_back_when_an_item_is_dropped() {
        let (tx, mut rx) = inbound_queue(3);
        assert_eq!(tx.max_batch(), 3);
        tx.try_send(status()).unwrap();
        tx.try_send(status()).unwrap();
        let frames = Inbound::Frames {
            link: 0,
            frames: vec![],
        };
        // An empty batch still takes one unit: the queue's third.
        tx.try_send(frames).unwrap();
        assert_eq!(tx.try_send(status()), Err(Refused::Full));
        let first = rx.recv().await.unwrap();
        assert_eq!(
            tx.try_send(status()),
            Err(Refused::Full),
            "held until dropped"
        );
        drop(first);
        tx.try_send(status()).unwrap();
        // A replay waits for room, and gets it once the service drops what it took.
        let waiting = tokio::spawn({
            let tx = tx.clone();
            async move { tx.send(status()).await }
        });
        tokio::task::yield_now().await;
        assert!(!waiting.is_finished());
        let mut taken = Vec::new();
        assert_eq!(rx.recv_many(&mut taken, 10).await, 3);
        taken.clear();
        waiting.await.unwrap().unwrap();
        drop(rx);
        assert_eq!(tx.try_send(status()), Err(Refused::Closed));
    }
}

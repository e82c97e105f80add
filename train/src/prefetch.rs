//! Reading the next training sample while the current one computes.
//!
//! Sample `s` of a run's stream is a pure function of `(seed, s)` ([`crate::source`]), so the
//! next sample this process trains on can be read and decoded (PNG images, masks, cameras) or
//! generated (a procedural subject) on another thread while the current one runs: the training
//! thread then only turns host data into tensors. One sample ahead is enough: preparing one
//! takes a fraction of a step. Which samples are this process's is a
//! [`BatchLayout`]'s choice (consecutive ones, or its rank's share of each batch).
//!
//! Order and content are exactly what [`TrainingSource::sample`] gives, so resuming and
//! profiling see the same data as the serial loop.

use std::sync::Arc;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use crate::data_parallel::BatchLayout;
use crate::source::{StepSample, TrainingSource};
use crate::trainer::TrainError;

type Prepared = (u64, Result<StepSample, TrainError>);

/// A background reader of the samples a [`BatchLayout`] gives this process, in order.
#[derive(Debug)]
pub struct Prefetcher {
    /// How many samples were handed out.
    taken: u64,
    layout: BatchLayout,
    seed: u64,
    source: Arc<TrainingSource>,
    receiver: Receiver<Prepared>,
    worker: Option<JoinHandle<()>>,
}

impl Prefetcher {
    /// Starts preparing the samples `layout` gives this process, of `source` under `seed`, one
    /// ahead of the consumer.
    pub fn new(source: Arc<TrainingSource>, seed: u64, layout: BatchLayout) -> Self {
        // Capacity 1: the worker holds one finished sample in the channel and prepares the
        // next one, so it never runs more than two steps ahead.
        let (sender, receiver) = sync_channel(1);
        let worker = std::thread::Builder::new()
            .name("lifegom-prefetch".into())
            .spawn({
                let source = source.clone();
                move || produce(&source, seed, layout, &sender)
            })
            .ok();
        Self {
            taken: 0,
            layout,
            seed,
            source,
            receiver,
            worker,
        }
    }

    /// The next sample (each call advances by one). If the worker thread could not be started
    /// or has stopped, the sample is prepared on this thread instead.
    pub fn next_sample(&mut self) -> Result<StepSample, TrainError> {
        let step = self.layout.sample_index(self.taken);
        self.taken += 1;
        let _span = tracing::debug_span!("data_wait").entered();
        match self.receiver.recv() {
            Ok((s, sample)) if s == step => sample,
            _ => self.source.sample(self.seed, step),
        }
    }
}

fn produce(source: &TrainingSource, seed: u64, layout: BatchLayout, sender: &SyncSender<Prepared>) {
    for step in (0..).map(|i| layout.sample_index(i)) {
        let sample = source.sample(seed, step);
        // The consumer dropped the prefetcher: stop.
        if sender.send((step, sample)).is_err() {
            return;
        }
    }
}

impl Drop for Prefetcher {
    fn drop(&mut self) {
        // Unblock the worker's pending `send` by dropping the receiver first, then join it so no
        // thread outlives the loop that owned it.
        let (_, dead) = sync_channel(0);
        drop(std::mem::replace(&mut self.receiver, dead));
        if let Some(worker) = self.worker.take() {
            let _ = worker.join();
        }
    }
}

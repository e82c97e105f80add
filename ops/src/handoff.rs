//! A gradient that one backward node hands to another instead of registering it (design.md
//! §7.5).
//!
//! When a tensor feeds two ops, Burn's autodiff adds the two gradients it receives with a launch
//! of its own. When both ops are ours and the second to run backward launches a kernel that
//! writes the tensor's gradient anyway, the first can hand its gradient over instead, and the
//! kernel adds it as it writes: one launch fewer per such tensor and pass. The first node
//! [`file`](Handoff::file)s, the second [`take`](Handoff::take)s.
//!
//! A handoff must join exactly one giver to one taker whose backward runs later (Burn runs
//! deeper nodes first), both for the same tensor: a gradient filed and never taken is lost. The
//! model's blocks join their own ops; the public functions join nothing
//! ([`Handoff::none`]).

use std::any::Any;
use std::sync::{Arc, Mutex, PoisonError};

/// What a giver filed, until the taker takes it.
type Slot = Mutex<Option<Box<dyn Any + Send>>>;

/// The slot a giver files its gradient in, shared by both nodes; or no joining.
#[derive(Clone, Default)]
pub struct Handoff(Option<Arc<Slot>>);

impl std::fmt::Debug for Handoff {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.is_joined() {
            "Handoff"
        } else {
            "Handoff(none)"
        })
    }
}

impl Handoff {
    /// A handoff between two nodes.
    pub fn new() -> Self {
        Self(Some(Arc::default()))
    }

    /// No joining: each node registers its own gradients.
    pub fn none() -> Self {
        Self(None)
    }

    /// Whether the handoff joins two nodes.
    pub fn is_joined(&self) -> bool {
        self.0.is_some()
    }

    /// Files `value` for the taker; `false` (and `value` dropped) when nothing is joined, and
    /// the giver registers the gradient itself.
    pub fn file<T: Any + Send>(&self, value: T) -> bool {
        let Some(slot) = &self.0 else {
            return false;
        };
        *slot.lock().unwrap_or_else(PoisonError::into_inner) = Some(Box::new(value));
        true
    }

    /// The filed value, if any.
    ///
    /// # Panics
    ///
    /// If the filed value is not a `T` (the two nodes run on different backends).
    pub fn take<T: Any + Send>(&self) -> Option<T> {
        let slot = self.0.as_ref()?;
        let filed = slot.lock().unwrap_or_else(PoisonError::into_inner).take()?;
        Some(
            *filed
                .downcast::<T>()
                .expect("both ends of a handoff run on one backend"),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A joined handoff hands the value over once; an unjoined one refuses it.
    #[test]
    fn hands_over_once() {
        let joined = Handoff::new();
        let taker = joined.clone();
        assert_eq!(taker.take::<u32>(), None);
        assert!(joined.file(7u32));
        assert_eq!(taker.take::<u32>(), Some(7));
        assert_eq!(taker.take::<u32>(), None);
        let none = Handoff::none();
        assert!(!none.file(7u32));
        assert_eq!(none.take::<u32>(), None);
    }
}

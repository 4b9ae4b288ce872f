//! The registry of stage calls a service is running, so `CancelStage(job_id)` can stop one.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use tokio_util::sync::CancellationToken;

/// Running stage calls by job id. Cloning shares the registry.
#[derive(Clone, Default)]
pub struct StageRegistry {
    running: Arc<Mutex<HashMap<String, CancellationToken>>>,
}

/// Removes its job from the registry when dropped (the stage call ended, however it ended).
pub struct StageGuard {
    registry: StageRegistry,
    job_id: String,
    token: CancellationToken,
}

impl StageGuard {
    /// Cancelled when the orchestrator asked this stage to stop.
    pub fn token(&self) -> &CancellationToken {
        &self.token
    }
}

impl Drop for StageGuard {
    fn drop(&mut self) {
        if let Ok(mut running) = self.registry.running.lock() {
            running.remove(&self.job_id);
        }
    }
}

impl StageRegistry {
    /// Registers a stage call for `job_id`. A retried call for the same job replaces (and cancels)
    /// the older one, which the orchestrator has given up on.
    pub fn start(&self, job_id: &str) -> StageGuard {
        let token = CancellationToken::new();
        if let Ok(mut running) = self.running.lock()
            && let Some(old) = running.insert(job_id.to_string(), token.clone())
        {
            old.cancel();
        }
        StageGuard { registry: self.clone(), job_id: job_id.to_string(), token }
    }

    /// Cancels the stage call running for `job_id`; false when none runs.
    pub fn cancel(&self, job_id: &str) -> bool {
        match self.running.lock() {
            Ok(running) => running.get(job_id).map(|t| t.cancel()).is_some(),
            Err(_) => false,
        }
    }

    /// How many stage calls are running.
    pub fn len(&self) -> usize {
        self.running.lock().map(|r| r.len()).unwrap_or(0)
    }

    /// True when no stage call is running.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cancel_reaches_the_running_call_and_the_guard_unregisters() {
        let reg = StageRegistry::default();
        assert!(!reg.cancel("j1"));
        let guard = reg.start("j1");
        assert_eq!(reg.len(), 1);
        assert!(reg.cancel("j1"));
        assert!(guard.token().is_cancelled());
        drop(guard);
        assert!(reg.is_empty());
        assert!(!reg.cancel("j1"));
    }
}

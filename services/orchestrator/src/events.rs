//! Change notifications: whoever changes a job publishes its id; watchers (SSE, `WatchJob`)
//! re-read the job and send it when its status, stage or progress changed.

use tokio::sync::{Notify, broadcast};

/// In-process hub of job changes and of "new work" for the workers.
pub struct EventHub {
    changed: broadcast::Sender<String>,
    work: Notify,
}

impl Default for EventHub {
    fn default() -> Self {
        Self { changed: broadcast::channel(4096).0, work: Notify::new() }
    }
}

impl EventHub {
    /// Job `id` changed.
    pub fn job_changed(&self, id: &str) {
        let _ = self.changed.send(id.to_string());
    }

    /// A job became runnable: wake one idle worker.
    pub fn work_available(&self) {
        self.work.notify_one();
    }

    pub fn subscribe(&self) -> broadcast::Receiver<String> {
        self.changed.subscribe()
    }

    /// Completes when [`EventHub::work_available`] is called (or was called while nobody waited).
    pub async fn wait_for_work(&self) {
        self.work.notified().await;
    }
}

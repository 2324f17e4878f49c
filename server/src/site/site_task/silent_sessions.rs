//! Sessions whose robot falls silent: when each was last heard of, and ending those silent past the
//! idle timeout.

use tracing::Instrument as _;

use super::{SiteTask, session_span};
use crate::site::SiteMap;

impl SiteTask {
    /// Notes a request of `session`'s robot (only sessions the map knows and has not closed are kept).
    pub(super) fn heard(&mut self, session: &str) {
        let open = self
            .map
            .as_ref()
            .is_some_and(|m| m.session_robot(session).is_some() && !m.is_closed(session));
        if open {
            self.last_heard
                .insert(session.to_owned(), tokio::time::Instant::now());
        }
    }

    /// Ends every open session silent for longer than the idle timeout.
    pub(super) async fn end_silent_sessions(&mut self) {
        let Some(timeout) = self.session_idle_timeout else {
            return;
        };
        let Ok(open) = self.map().map(SiteMap::open_sessions) else {
            return;
        };
        let now = tokio::time::Instant::now();
        // Every open session is heard of at the task's start and at its open; one that somehow was
        // not counts as silent from now on.
        let silent: Vec<(String, String)> = open
            .into_iter()
            .filter(|(session, _)| {
                let heard = *self.last_heard.entry(session.clone()).or_insert(now);
                now.duration_since(heard) > timeout
            })
            .collect();
        for (session, robot) in silent {
            let span = session_span(&robot, &session);
            match self
                .close_session(&robot, &session)
                .instrument(span.clone())
                .await
            {
                Ok(version) => {
                    self.metrics.session_timed_out();
                    span.in_scope(|| {
                        tracing::info!(
                            version,
                            silent_s = timeout.as_secs_f64(),
                            "session ended: its robot was silent past the idle timeout"
                        );
                    });
                }
                Err(e) => span.in_scope(|| tracing::warn!("cannot end a silent session: {e}")),
            }
        }
    }
}

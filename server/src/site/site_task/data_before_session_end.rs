//! Robots' data before session-end maintenance: a session end waits behind another session's queued
//! upload (see the module docs of `site_task`).

use tokio::sync::mpsc;

use super::SiteTask;
use crate::site::site_handle::Command;

/// Most times in a row a session end is put behind another robot's upload (see
/// [`SiteTask::data_before_session_end`]).
const MAX_SESSION_END_DEFERRALS: u32 = 16;

/// Most commands taken off the queue into the backlog (the queue's own capacity).
const MAX_BACKLOG: usize = 64;

impl SiteTask {
    /// Robots' data before session-end maintenance: if `command` ends a session and another session's
    /// upload that does not is queued, that upload is handled now and `command` waits at the head of
    /// the backlog — at most [`MAX_SESSION_END_DEFERRALS`] times in a row, so a busy site still ends its
    /// sessions. Ending a session (the final optimization, trimming, sparsification: seconds of CPU when
    /// a fleet's sessions end together) answers nobody in real time; another robot's upload carries
    /// submaps the fleet waits for. The log records the order the changes were applied in, so a replay
    /// rebuilds the same map.
    pub(super) fn data_before_session_end(
        &mut self,
        command: Command,
        commands: &mut mpsc::Receiver<Command>,
    ) -> Command {
        let Some(session) = command.session().filter(|_| command.ends_session()) else {
            return command;
        };
        if self.session_end_deferrals >= MAX_SESSION_END_DEFERRALS {
            self.session_end_deferrals = 0;
            return command;
        }
        while self.backlog.len() < MAX_BACKLOG {
            match commands.try_recv() {
                Ok(queued) => self.backlog.push_back(queued),
                Err(_) => break,
            }
        }
        let Some(data) = self
            .backlog
            .iter()
            .position(|queued| queued.is_data_of_another_session(session))
            .and_then(|i| self.backlog.remove(i))
        else {
            self.session_end_deferrals = 0;
            return command;
        };
        self.session_end_deferrals += 1;
        self.backlog.push_front(command);
        data
    }
}

//! [`MapUplink`] to an in-process fake server, for tests: it enforces the server's sequence rules
//! (duplicates acknowledged once, gaps refused, nothing new accepted into a closed session, unknown sessions
//! not closable), can be taken offline, and records what it applied.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, MutexGuard};

use proto::{MapDelta, pb};
use tokio::sync::watch;

use super::{Acked, MapUplink, OpenedSession, UplinkError, VersionStream};

#[derive(Default)]
struct State {
    online: bool,
    version: u64,
    sessions: BTreeMap<String, (u32, u64, bool)>,
    applied: Vec<pb::UploadBatch>,
    duplicates: usize,
}

/// A fake server shared by clones: clone it to keep a handle for inspection.
#[derive(Clone)]
pub struct InMemoryUplink {
    site: String,
    state: Arc<Mutex<State>>,
    versions: Arc<watch::Sender<u64>>,
}

impl InMemoryUplink {
    /// An online fake server for `site`.
    pub fn new(site: &str) -> Self {
        Self {
            site: site.to_owned(),
            state: Arc::new(Mutex::new(State {
                online: true,
                ..State::default()
            })),
            versions: Arc::new(watch::channel(0).0),
        }
    }

    fn state(&self) -> MutexGuard<'_, State> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Takes the link down (every call fails with [`UplinkError::Unavailable`]) or brings it back.
    pub fn set_online(&self, online: bool) {
        self.state().online = online;
    }

    /// Every batch applied, in order.
    pub fn applied(&self) -> Vec<pb::UploadBatch> {
        self.state().applied.clone()
    }

    /// Whether `session_uuid` is known and closed.
    pub fn is_closed(&self, session_uuid: &str) -> bool {
        self.state().sessions.get(session_uuid).is_some_and(|s| s.2)
    }

    /// Closes a session as the server does on its own (its robot silent past the idle timeout).
    pub fn close_as_server(&self, session_uuid: &str) {
        if let Some(session) = self.state().sessions.get_mut(session_uuid) {
            session.2 = true;
        }
    }

    /// Batches received again after being applied.
    pub fn duplicates(&self) -> usize {
        self.state().duplicates
    }

    fn online(&self) -> Result<MutexGuard<'_, State>, UplinkError> {
        let state = self.state();
        if state.online {
            Ok(state)
        } else {
            Err(UplinkError::unavailable("in-memory link is down"))
        }
    }

    fn bump(&self, state: &mut State) -> u64 {
        state.version += 1;
        self.versions.send_replace(state.version);
        state.version
    }
}

impl MapUplink for InMemoryUplink {
    async fn open_session(
        &mut self,
        _robot_id: &str,
        session_uuid: &str,
    ) -> Result<OpenedSession, UplinkError> {
        let mut state = self.online()?;
        let next = state.sessions.len() as u32;
        let created = !state.sessions.contains_key(session_uuid);
        let (trajectory, last, _) = *state
            .sessions
            .entry(session_uuid.to_owned())
            .or_insert((next, 0, false));
        let map_version = if created {
            self.bump(&mut state)
        } else {
            state.version
        };
        Ok(OpenedSession {
            trajectory,
            last_acked_seq: last,
            created,
            map_version,
        })
    }

    async fn upload(&mut self, batch: &pb::UploadBatch) -> Result<Acked, UplinkError> {
        let mut state = self.online()?;
        let Some(&(_, last, closed)) = state.sessions.get(&batch.session_uuid) else {
            return Err(UplinkError::Rejected {
                code: tonic::Code::NotFound,
                message: "unknown session".into(),
            });
        };
        if batch.seq <= last {
            state.duplicates += 1;
            return Ok(Acked {
                seq: batch.seq,
                map_version: state.version,
                duplicate: true,
                session_end_pose: None,
            });
        }
        if batch.seq != last + 1 {
            return Err(UplinkError::SequenceGap { expected: last + 1 });
        }
        if closed {
            return Err(UplinkError::Rejected {
                code: tonic::Code::FailedPrecondition,
                message: format!("session {:?} is closed", batch.session_uuid),
            });
        }
        if let Some(session) = state.sessions.get_mut(&batch.session_uuid) {
            session.1 = batch.seq;
        }
        state.applied.push(batch.clone());
        let map_version = self.bump(&mut state);
        Ok(Acked {
            seq: batch.seq,
            map_version,
            duplicate: false,
            session_end_pose: None,
        })
    }

    async fn close_session(
        &mut self,
        _robot_id: &str,
        session_uuid: &str,
    ) -> Result<u64, UplinkError> {
        let mut state = self.online()?;
        let closed = state
            .sessions
            .get_mut(session_uuid)
            .map(|s| std::mem::replace(&mut s.2, true));
        match closed {
            Some(false) => Ok(self.bump(&mut state)),
            Some(true) => Ok(state.version),
            None => Err(UplinkError::Rejected {
                code: tonic::Code::NotFound,
                message: format!("unknown session {session_uuid:?}: open it first"),
            }),
        }
    }

    async fn map_version(&mut self) -> Result<u64, UplinkError> {
        Ok(self.online()?.version)
    }

    async fn delta_since(&mut self, since: u64) -> Result<MapDelta, UplinkError> {
        let state = self.online()?;
        Ok(MapDelta {
            site: self.site.clone(),
            from_version: since,
            to_version: state.version,
            submaps_added: Vec::new(),
            pose_updates: Vec::new(),
            trimmed: Vec::new(),
        })
    }

    async fn watch_versions(&mut self) -> Result<VersionStream, UplinkError> {
        drop(self.online()?);
        let stream = tokio_stream::wrappers::WatchStream::new(self.versions.subscribe());
        Ok(Box::pin(tokio_stream::StreamExt::map(stream, Ok)))
    }
}

//! The calling thread's side of [`super::run_session_inputs`]: LLO driven over each session's events,
//! its nodes and session ends sent to the map worker, and what that leaves to assemble the run from
//! (each scan's anchor, each node's LLO pose and range data, the sessions' spans and scan counts).

use std::collections::BTreeMap;

use mapping::geometry::Rigid2;
use mapping::local_slam::{LloDriver, LloEvent};
use mapping::pose_graph::NodeId;
use mapping::sensor::{RangeData, SensorEvent, Timestamp};

use super::carried_nodes::place_carried;
use super::map_worker::{Message, WorkerOutput};
use super::{ScanAnchor, SessionInput, SessionsConfig, SessionsRun, active_grids};

/// What LLO produced over the sessions fed so far.
#[derive(Default)]
pub(super) struct SessionFeed {
    /// Every matched scan, in order.
    anchors: Vec<ScanAnchor>,
    /// Each node's LLO pose and range data.
    node_data: BTreeMap<NodeId, (Rigid2, RangeData)>,
    /// Scans per session.
    scans_per_session: Vec<usize>,
    /// Each session's first event time (the previous one's for an empty session).
    boundaries: Vec<Timestamp>,
    /// The sum of each session's first-to-last event span, seconds.
    data_duration_s: f64,
    /// Scans fed, all sessions.
    pub(super) scans_done: usize,
    /// The id of the first session fed (a resumed run's: see [`super::RunResume`]); the books above are
    /// per session from it.
    pub(super) first_session: u32,
}

impl SessionFeed {
    /// A feed whose first session is `first_session`.
    pub(super) fn starting_at(first_session: u32) -> Self {
        Self {
            first_session,
            ..Self::default()
        }
    }

    /// Drives a fresh LLO over `input` as session `session`, sending `send` its start, each node and its
    /// end. `false` once the worker has stopped (its error is reported by joining it).
    pub(super) fn feed(
        &mut self,
        session: u32,
        input: &SessionInput,
        config: &SessionsConfig,
        send: &dyn Fn(Message) -> bool,
        progress: &mut dyn FnMut(usize),
    ) -> bool {
        let (Some(first), Some(last)) = (input.events.first(), input.events.last()) else {
            // An empty session still exists (its id is used) but adds nothing.
            self.scans_per_session.push(0);
            self.boundaries
                .push(self.boundaries.last().copied().unwrap_or_default());
            return true;
        };
        self.boundaries.push(first.time());
        self.data_duration_s += last.time().seconds_since(first.time());
        let mut scans = 0usize;
        let mut session_anchors: Vec<ScanAnchor> = Vec::new();
        let mut llo = LloDriver::new(config.local.clone());
        let mut next_index = 0u32;
        let mut last_node: Option<NodeId> = None;
        let mut alive = send(Message::Start {
            session,
            start_time: first.time(),
            from_dock: input.from_dock,
        });
        for event in mapping::sensor::collate_for_llo(&input.events) {
            if matches!(event, SensorEvent::Scan(_)) {
                self.scans_done += 1;
                scans += 1;
            }
            let LloEvent::ScanMatched {
                result, range_data, ..
            } = llo.add_event(event, &input.base_from_laser)
            else {
                continue;
            };
            if let Some(insertion) = result.insertion {
                let id = NodeId {
                    trajectory: session,
                    index: next_index,
                };
                next_index += 1;
                last_node = Some(id);
                self.node_data.insert(id, (result.local_pose, range_data));
                let message = Message::Node {
                    session,
                    node: insertion.into_llo_node(),
                };
                alive = alive && send(message);
                if !alive {
                    break;
                }
            }
            let anchor = ScanAnchor {
                time: result.time,
                local_pose: result.local_pose,
                node: last_node,
            };
            self.anchors.push(anchor);
            session_anchors.push(anchor);
            if self.scans_done.is_multiple_of(64) {
                progress(self.scans_done);
            }
        }
        self.scans_per_session.push(scans);
        alive
            && send(Message::Finish {
                session,
                active_submaps: active_grids(llo.builder()),
                scans: session_anchors,
            })
    }

    /// The run: each scan's final global pose (from the final map where its node is still there; a
    /// trimmed node carried with the nearest node the map kept, see [`super::carried_nodes`]; else the last
    /// estimate before its node went), each session's span and scan count.
    pub(super) fn into_run(self, output: WorkerOutput) -> SessionsRun {
        let WorkerOutput {
            map,
            mut sessions,
            retired,
            carried,
            records,
            probe_poses,
        } = output;
        let mut node_pose: BTreeMap<NodeId, Rigid2> = retired;
        for (id, _, pose) in map.node_poses() {
            node_pose.insert(id, pose);
        }
        place_carried(&mut node_pose, &carried);
        let node_data = self.node_data;
        let scan_pose = |poses: &BTreeMap<NodeId, Rigid2>, a: &ScanAnchor| {
            let node = a.node?;
            let global = poses.get(&node)?;
            let (local, _) = node_data.get(&node)?;
            Some((a.time, global * local.inverse() * a.local_pose))
        };
        let scan_poses = self
            .anchors
            .iter()
            .filter_map(|a| scan_pose(&node_pose, a))
            .collect();
        for summary in &mut sessions {
            let k = (summary.session - self.first_session) as usize;
            summary.start_time = self.boundaries[k];
            summary.scans = self.scans_per_session[k];
        }
        let node_range_data = node_data
            .into_iter()
            .filter_map(|(id, (_, data))| Some((id, (*node_pose.get(&id)?, data))))
            .collect();
        SessionsRun {
            scan_poses,
            boundaries: self.boundaries,
            sessions,
            map,
            node_range_data,
            data_duration_s: self.data_duration_s,
            records,
            probe_poses,
            scans_retimed: 0,
        }
    }
}

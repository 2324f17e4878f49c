//! A robot's cleaning session run through LLO, its session start and its GLM ahead of time (phase 2 of
//! `load`, not measured): robots run those on their own CPUs, so doing them ahead keeps them off the
//! server's cores and the measured figures are the server's.

use anyhow::Context as _;
use mapping::geometry::Rigid2;
use mapping::global_slam::GlobalSlamOptions;
use mapping::lifelong::{MapMatcher, RelocalizationOptions, SessionStartOptions};
use mapping::local_slam::LocalTrajectoryBuilderOptions;
use proto::{SubmapSnapshot, UploadItem};
use robot_agent::source::{ReadReport, Recording};
use robot_agent::uplink::{cached_submaps, match_node, place_ahead, run_llo, sync_matcher};
use simulator::{SessionOptions as SimSessionOptions, Store};

use crate::load_fleet::Robot;

/// A robot's cleaning session, run through LLO ahead of time.
pub(crate) struct PreparedSession {
    /// One entry per node: its items (the node, then the submaps it finished).
    pub steps: Vec<Vec<UploadItem>>,
    /// `global_from_local` where the robot's session start placed it.
    pub prior: Option<Rigid2>,
    pub duration_s: f64,
}

/// What [`prepare_sessions`] prepared.
pub(crate) struct Prepared {
    /// Per robot, its sessions in the order it streams them.
    pub sessions: Vec<Vec<PreparedSession>>,
    /// GLM matches the robots found ahead of time.
    pub glm_matches: u64,
}

/// Simulates every robot's sessions of `lengths` (seconds of robot time each, on consecutive days of
/// the robot's schedule: robot k of a site cleans on day 1 + k, then every `robots_per_site` days) in
/// its site's world, runs them through LLO, places each with the robot's session start against the
/// robot's cache of the site map, and (unless `glm_on_server`) runs the robot's GLM over its nodes
/// against that cache.
pub(crate) async fn prepare_sessions(
    robots: &[Robot],
    worlds: &[Store],
    lengths: &[f64],
    robots_per_site: usize,
    glm_on_server: bool,
) -> anyhow::Result<Prepared> {
    let sites = worlds.len();
    let mut preparing = Vec::new();
    for (r, robot) in robots.iter().enumerate() {
        for (j, &length) in lengths.iter().enumerate() {
            let world = worlds[robot.site].clone();
            let sim = SimSessionOptions {
                max_duration_s: length,
                ..SimSessionOptions::default()
            };
            // Robot k of a site cleans on day 1 + k, then every robots_per_site days.
            let session = u32::try_from(1 + r / sites + j * robots_per_site)?;
            preparing.push((
                r,
                tokio::task::spawn_blocking(
                    move || -> anyhow::Result<(Vec<Vec<UploadItem>>, f64)> {
                        let simulated = world.session(session, &sim)?;
                        let recording = Recording::from_unsorted(
                            simulated.events,
                            simulated.base_from_laser,
                            ReadReport::default(),
                        );
                        let mut steps = Vec::new();
                        run_llo(
                            &recording,
                            &LocalTrajectoryBuilderOptions::default(),
                            0.0,
                            None,
                            &mut |items| {
                                steps.push(items);
                                true
                            },
                        );
                        Ok((steps, simulated.duration_s))
                    },
                ),
            ));
        }
    }
    let mut sessions: Vec<Vec<PreparedSession>> = robots.iter().map(|_| Vec::new()).collect();
    let mut glm_matches = 0;
    for (r, task) in preparing {
        let robot = &robots[r];
        let (mut steps, duration_s) = task.await.context("LLO thread")??;
        let prior = place_ahead(
            &robot.cache,
            &RelocalizationOptions::default(),
            &SessionStartOptions::default(),
            steps.iter().flatten(),
        )
        .await?;
        // GLM on the robot, also ahead of time (robots match on their own CPUs), against the robot's
        // cache of the site as it was when the session started (session 0's map).
        if let (false, Some(global_from_local)) = (glm_on_server, prior) {
            let submaps = cached_submaps(
                &*robot
                    .cache
                    .lock()
                    .map_err(|_| anyhow::anyhow!("a robot's cache lock is poisoned"))?,
                None,
            );
            let (matched, count) = tokio::task::spawn_blocking(move || {
                robot_glm_ahead(steps, &submaps, global_from_local)
            })
            .await
            .context("GLM thread")??;
            steps = matched;
            glm_matches += count;
        }
        sessions[r].push(PreparedSession {
            steps,
            prior,
            duration_s,
        });
    }
    Ok(Prepared {
        sessions,
        glm_matches,
    })
}

/// Matches every node of a prepared session against the given site submaps, as the robot's GLM would,
/// and appends the accepted matches to its items. Returns the steps and the number of matches.
fn robot_glm_ahead(
    mut steps: Vec<Vec<UploadItem>>,
    submaps: &[SubmapSnapshot],
    global_from_local: Rigid2,
) -> anyhow::Result<(Vec<Vec<UploadItem>>, u64)> {
    let mut matcher = MapMatcher::new(
        GlobalSlamOptions::default().constraint_builder,
        global_from_local,
    )?;
    sync_matcher(&mut matcher, submaps);
    let mut count = 0;
    for items in &mut steps {
        let Some(UploadItem::NodeAdded(node)) = items.first() else {
            continue;
        };
        let found = match_node(&mut matcher, node);
        count += found.len() as u64;
        items.extend(found);
    }
    Ok((steps, count))
}

/// Lengths of a robot's consecutive sessions, seconds of robot time: `duration_s` cut into sessions
/// of `session_s` (the last one shorter), or one session of `duration_s`.
pub(crate) fn session_lengths(duration_s: f64, session_s: Option<f64>) -> Vec<f64> {
    let Some(session_s) = session_s.filter(|s| *s > 0.0) else {
        return vec![duration_s];
    };
    let mut lengths = Vec::new();
    let mut left = duration_s;
    // Bounded: at most 3600 / 30 sessions with validated arguments.
    while left > 1e-6 && lengths.len() < 10_000 {
        lengths.push(left.min(session_s));
        left -= session_s;
    }
    lengths
}

#[cfg(test)]
mod tests {
    use super::session_lengths;

    #[test]
    fn a_duration_is_cut_into_back_to_back_sessions() {
        assert_eq!(session_lengths(120.0, None), vec![120.0]);
        assert_eq!(session_lengths(1800.0, Some(300.0)), vec![300.0; 6]);
        assert_eq!(
            session_lengths(700.0, Some(300.0)),
            vec![300.0, 300.0, 100.0]
        );
        assert_eq!(session_lengths(100.0, Some(300.0)), vec![100.0]);
    }
}

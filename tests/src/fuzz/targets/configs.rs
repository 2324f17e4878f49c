//! TOML configurations: the server's (`evermap-server serve`), the offline SLAM one (`offline`,
//! `relocalize`) and the multi-session one (`sessions`, `lifelong`). Each is parsed and validated as its
//! command does, and an accepted one builds what it configures (LLO fed two scans of a small room, global
//! SLAM, the lifelong map), so a value that validates but makes the core allocate gigabytes or panic is
//! found too. `evermap-agent run`'s `AgentConfig` is parsed and validated by the library
//! (`robot_agent::agent_config`), as the binary does, and builds its zenoh configurations, the live
//! decoder of its `[ros2]` section and LLO.

use std::path::Path;

use mapping::geometry::rigid2;
use mapping::global_slam::GlobalSlam;
use mapping::lifelong::LifelongMap;
use mapping::local_slam::{LocalTrajectoryBuilder, LocalTrajectoryBuilderOptions};
use mapping::sensor::{LaserScan, OdometryReading, Timestamp};
use robot_agent::agent_config::AgentConfig;
use robot_agent::lifelong_run::SessionsConfig;
use robot_agent::offline_slam::SlamConfig;
use robot_agent::source::LiveDecoder;
use server::ServerConfig;

use super::super::fuzz_target::{FuzzTarget, Verdict};
use super::{SetupError, read_file};

/// A 10 m × 6 m room seen from its middle: 181 beams over 180°.
fn room_scan(time: Timestamp) -> LaserScan {
    let n = 181;
    let increment = std::f32::consts::PI / (n - 1) as f32;
    let ranges = (0..n)
        .map(|i| {
            let angle = -std::f32::consts::FRAC_PI_2 + i as f32 * increment;
            let (s, c) = angle.sin_cos();
            let to_x = if c.abs() > 1e-6 {
                5.0 / c.abs()
            } else {
                f32::MAX
            };
            let to_y = if s.abs() > 1e-6 {
                3.0 / s.abs()
            } else {
                f32::MAX
            };
            to_x.min(to_y)
        })
        .collect();
    LaserScan {
        time,
        angle_min: -std::f32::consts::FRAC_PI_2,
        angle_increment: increment,
        time_increment: 0.0,
        range_min: 0.1,
        range_max: 30.0,
        ranges,
    }
}

/// LLO with `options`, fed odometry and two scans.
fn drive_llo(options: &LocalTrajectoryBuilderOptions) {
    let mut llo = LocalTrajectoryBuilder::new(options.clone());
    for k in 0..2_i64 {
        let time = Timestamp(1_000_000_000 + k * 100_000_000);
        llo.add_odometry(&OdometryReading {
            time,
            pose: rigid2(0.01 * k as f64, 0.0, 0.0),
        });
        let (range_data, _) = room_scan(time).to_range_data(&options.range_conversion);
        let _ = llo.add_range_data(time, &range_data);
    }
}

/// A configuration target's input as text (a refusal if it is not UTF-8).
fn text(input: &[u8]) -> Result<&str, Verdict> {
    refused(std::str::from_utf8(input))
}

/// A step's error as the input's refusal, so that a target's steps chain with `?`.
fn refused<T, E: std::fmt::Display>(result: Result<T, E>) -> Result<T, Verdict> {
    result.map_err(|e| Verdict::Rejected(e.to_string()))
}

/// Runs a target's steps: their verdict, or the first step's refusal.
fn verdict(steps: impl FnOnce() -> Result<Verdict, Verdict>) -> Verdict {
    steps().unwrap_or_else(|refusal| refusal)
}

fn deploy_file(name: &str) -> Result<Vec<u8>, SetupError> {
    read_file(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../deploy")
            .join(name),
    )
}

fn local_section() -> Result<String, SetupError> {
    let mut table = toml::Table::new();
    table.insert(
        "local".into(),
        toml::Value::try_from(LocalTrajectoryBuilderOptions::default()).map_err(|e| {
            SetupError::Seed {
                path: "<default local options>".into(),
                reason: e.to_string(),
            }
        })?,
    );
    toml::to_string(&table).map_err(|e| SetupError::Seed {
        path: "<default local options>".into(),
        reason: e.to_string(),
    })
}

const GLOBAL_SECTION: &str = "[global]\noptimize_every_n_nodes = 90\nodometry_translation_sigma = 0.05\n\
    odometry_rotation_sigma = 0.01\nloop_closure_retraction_chi2 = 30.0\n";

const LIFELONG_SECTION: &str = "[lifelong]\npolicy = \"clt\"\noptimize_every_n_sparsifications = 5\n\
    sparsification_max_iterations = 10\n[lifelong.session_start]\nhold_back_nodes = 10\nretry_every_n_nodes = 20\n\
    max_search_nodes = 80\nprobation_matches = 3\nprobation_min_separation_m = 3.0\nagreement_translation_m = 1.0\n\
    [lifelong.global]\noptimize_every_n_nodes = 90\n";

/// `evermap-server serve`'s configuration.
pub fn server_config() -> Result<FuzzTarget, SetupError> {
    let deploy = deploy_file("server.toml")?;
    let mut with_map = deploy.clone();
    with_map.extend_from_slice(
        b"\n[map]\npolicy = \"delete\"\n[map.session_start]\nhold_back_nodes = 5\n[map.global]\noptimize_every_n_nodes = 30\n",
    );
    let seeds = vec![
        deploy,
        with_map,
        b"[[sites]]\nid = \"s\"\nrobots = [{ id = \"r\", token = \"t\" }]\n".to_vec(),
    ];
    Ok(FuzzTarget::new(
        "server_config",
        "evermap-server TOML configuration (parse, validate, build the site map)",
        seeds,
        true,
        Box::new(|input| {
            verdict(|| {
                let config = refused(ServerConfig::from_toml(text(input)?))?;
                refused(config.validate())?;
                if let Some(zenoh) = &config.zenoh {
                    refused(zenoh.to_zenoh_config())?;
                }
                Ok(Verdict::of(&LifelongMap::new(config.map)))
            })
        }),
    ))
}

/// `offline` / `relocalize`'s SLAM configuration.
pub fn slam_config() -> Result<FuzzTarget, SetupError> {
    let local = local_section()?;
    let seeds = vec![
        local.clone().into_bytes(),
        format!("{local}\n{GLOBAL_SECTION}").into_bytes(),
        GLOBAL_SECTION.as_bytes().to_vec(),
    ];
    let mut target = FuzzTarget::new(
        "slam_config",
        "offline SLAM TOML configuration (parse, validate, run LLO on two scans, build global SLAM)",
        seeds,
        true,
        Box::new(|input| {
            verdict(|| {
                let config: SlamConfig = refused(toml::from_str(text(input)?))?;
                refused(config.local.validate())?;
                refused(config.relocalization.validate())?;
                refused(GlobalSlam::new(config.global.clone()))?;
                drive_llo(&config.local);
                Ok(Verdict::Accepted)
            })
        }),
    );
    // LLO's submaps and search windows: a fixed budget, whatever the file's size.
    target.base_heap_bytes = 256 << 20;
    Ok(target)
}

/// `sessions` / `lifelong`'s multi-session configuration.
pub fn sessions_config() -> Result<FuzzTarget, SetupError> {
    let local = local_section()?;
    let seeds = vec![
        format!("{local}\n{LIFELONG_SECTION}").into_bytes(),
        LIFELONG_SECTION.as_bytes().to_vec(),
        b"[scoring]\ninitialization_window_s = 30.0\n".to_vec(),
    ];
    let mut target = FuzzTarget::new(
        "sessions_config",
        "multi-session TOML configuration (parse, validate, run LLO on two scans, build the lifelong map)",
        seeds,
        true,
        Box::new(|input| {
            verdict(|| {
                let config: SessionsConfig = refused(toml::from_str(text(input)?))?;
                refused(config.local.validate())?;
                refused(config.scoring.validate())?;
                refused(LifelongMap::new(config.lifelong.clone()))?;
                drive_llo(&config.local);
                Ok(Verdict::Accepted)
            })
        }),
    );
    target.base_heap_bytes = 256 << 20;
    Ok(target)
}

/// A live robot's agent configuration, with `[ros2.publish]` and mutual TLS left out (its files must exist).
const LIVE_AGENT: &str = "site = \"store-1\"\nrobot_id = \"robot-1\"\ntoken = \"change-me\"\nreplay_speed = 0.0\n\
    nodes_per_batch = 5\ncall_timeout_s = 10.0\n[ros2]\ndomain_id = 7\nscan_topic = \"/base/scan\"\n\
    imu_topic = \"/imu\"\nreorder_window_s = 0.3\nqueue_capacity = 128\n[ros2.zenoh]\n\
    connect = [\"tcp/127.0.0.1:7447\"]\n[ros2.publish]\npose_topic = \"/amcl_pose\"\n";

/// `evermap-agent run`'s configuration.
pub fn agent_config() -> Result<FuzzTarget, SetupError> {
    let local = local_section()?;
    let mut with_local = deploy_file("agent-1.toml")?;
    with_local.push(b'\n');
    with_local.extend_from_slice(local.as_bytes());
    let seeds = vec![
        deploy_file("agent-1.toml")?,
        deploy_file("agent-2.toml")?,
        with_local,
        LIVE_AGENT.as_bytes().to_vec(),
    ];
    let mut target = FuzzTarget::new(
        "agent_config",
        "evermap-agent run TOML configuration (parse, validate, zenoh configs, live decoder, LLO on two scans)",
        seeds,
        true,
        Box::new(|input| {
            verdict(|| {
                let config = refused(AgentConfig::from_toml(text(input)?))?;
                refused(config.validate())?;
                if let Some(zenoh) = &config.zenoh {
                    refused(zenoh.to_zenoh_config())?;
                }
                if let Some(ros2) = &config.ros2 {
                    refused(ros2.zenoh.to_zenoh_config())?;
                    let decoder = LiveDecoder::new(ros2);
                    assert_eq!(
                        decoder.topic_count(),
                        4 + usize::from(ros2.imu_topic.is_some()),
                        "invariant: one topic index per subscription"
                    );
                }
                assert!(
                    config.call_timeout().is_ok()
                        && config.retry_interval().is_ok()
                        && config.final_flush_timeout().is_ok(),
                    "invariant: a validated configuration's durations convert"
                );
                drive_llo(&config.local);
                Ok(Verdict::Accepted)
            })
        }),
    );
    target.base_heap_bytes = 256 << 20;
    Ok(target)
}

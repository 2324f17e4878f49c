//! The load benchmark's fleet: one map server on a sled store, its robots (each a gRPC uplink and a
//! follower keeping its cache of the site map), and the mapping of every site by its robot 0 (phase 1 of
//! `load`, not measured).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use robot_agent::outbox::Outbox;
use robot_agent::source::{ReadReport, Recording};
use robot_agent::uplink::{
    GlobalSubmapCache, GrpcUplink, SessionOptions, Uploader, follow_site_with, stream_recording,
};
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use simulator::{SessionOptions as SimSessionOptions, Store};
use storage::{SledStore, SledStoreOptions};
use tokio::sync::watch;
use tokio::task::JoinHandle;
use tracing::Instrument as _;

use crate::demo_command::MAX_MESSAGE_BYTES;
use crate::idle_sites::{IdleSite, idle_sites};
use crate::load_command::LoadArgs;

/// One robot of the benchmark.
pub(crate) struct Robot {
    pub site: usize,
    pub id: String,
    pub uplink: GrpcUplink,
    pub cache: Arc<Mutex<GlobalSubmapCache>>,
    /// When each site version reached this robot's cache.
    pub arrivals: Arc<Mutex<Vec<(u64, Instant)>>>,
}

/// The server, its store and the robots following it.
pub(crate) struct Fleet {
    pub server: RunningServer,
    pub store: Arc<SledStore>,
    pub robots: Vec<Robot>,
    /// The server's gRPC URL.
    pub url: String,
    /// The sites of `--idle-store`, served beside the load's.
    pub idle_sites: Vec<IdleSite>,
    /// Every robot's follower, until [`Fleet::stop_following`].
    followers: Vec<JoinHandle<()>>,
    stop: watch::Sender<bool>,
    /// Turns true when the followers (and anything else watching it) should stop.
    pub stopped: watch::Receiver<bool>,
}

pub(crate) fn site_id(s: usize) -> String {
    format!("store-{}", s + 1)
}

impl Fleet {
    /// Opens the server's store under `args.out/data`, starts the server with `args.sites` sites and
    /// `args.agents` robots (robot r belongs to site r % sites), and starts every robot's follower.
    pub async fn start(args: &LoadArgs) -> anyhow::Result<Self> {
        let store_path = args
            .idle_store
            .clone()
            .unwrap_or_else(|| args.out.join("data"));
        let store_options = SledStoreOptions {
            path: store_path.clone(),
            cache_capacity_bytes: args.store_cache_mib << 20,
            ..SledStoreOptions::default()
        };
        store_options.validate()?;
        let store = tokio::task::spawn_blocking(move || SledStore::open(&store_options))
            .await
            .context("storage thread")??;

        // Robot r belongs to site r % sites; robot k of a site is named robot-<site>-<k>.
        let mut site_robots: Vec<Vec<RobotConfig>> = vec![Vec::new(); args.sites];
        for r in 0..args.agents {
            let s = r % args.sites;
            let k = site_robots[s].len();
            site_robots[s].push(RobotConfig {
                id: format!("robot-{}-{k}", s + 1),
                token: format!("load-token-{}-{k}", s + 1),
            });
        }
        let active: Vec<String> = (0..args.sites).map(site_id).collect();
        let idle_sites = idle_sites(&store, &active)?;
        let config = ServerConfig {
            listen: "127.0.0.1:0".parse()?,
            metrics_listen: None,
            max_message_bytes: MAX_MESSAGE_BYTES,
            sites: site_robots
                .iter()
                .enumerate()
                .map(|(s, robots)| SiteConfig {
                    id: site_id(s),
                    robots: robots.clone(),
                })
                .chain(idle_sites.iter().map(IdleSite::config))
                .collect(),
            checkpoints: if args.no_checkpoints {
                server::site::CheckpointOptions::DISABLED
            } else {
                server::site::CheckpointOptions::DEFAULT
            },
            ..ServerConfig::default()
        };
        let store = Arc::new(store);
        let server = RunningServer::start(&config, Arc::clone(&store) as Arc<_>).await?;
        let url = format!("http://{}", server.grpc_addr());
        eprintln!(
            "evermap load: server on {url} (sled in {}), {} robots on {} sites ({} idle sites beside them), {} s of robot time each at {}x real time",
            store_path.display(),
            args.agents,
            args.sites,
            idle_sites.len(),
            args.duration_s,
            args.speed
        );

        let (stop, stopped) = watch::channel(false);
        let mut robots = Vec::new();
        let mut followers = Vec::new();
        for (s, configs) in site_robots.iter().enumerate() {
            for config in configs {
                let uplink = GrpcUplink::new(
                    &url,
                    &site_id(s),
                    &config.token,
                    MAX_MESSAGE_BYTES,
                    Duration::from_secs(60),
                )?;
                let cache = Arc::new(Mutex::new(GlobalSubmapCache::default()));
                let arrivals = Arc::new(Mutex::new(Vec::new()));
                let record = Arc::clone(&arrivals);
                followers.push(tokio::spawn(follow_site_with(
                    uplink.clone(),
                    Arc::clone(&cache),
                    stopped.clone(),
                    Duration::from_millis(200),
                    move |version| {
                        if let Ok(mut a) = record.lock() {
                            a.push((version, Instant::now()));
                        }
                    },
                )));
                robots.push(Robot {
                    site: s,
                    id: config.id.clone(),
                    uplink,
                    cache,
                    arrivals,
                });
            }
        }
        Ok(Self {
            server,
            store,
            robots,
            url,
            idle_sites,
            followers,
            stop,
            stopped,
        })
    }

    /// Phase 1: every site's robot 0 maps its store (`worlds[s]`, session 0), streamed as fast as the
    /// server takes it; returns once every robot's cache holds its site's version.
    pub async fn map_stores(
        &self,
        worlds: &[Store],
        mapping_max_duration_s: f64,
    ) -> anyhow::Result<()> {
        let mapping_sim = SimSessionOptions {
            mapping_max_duration_s,
            ..SimSessionOptions::default()
        };
        let mut mappers = Vec::new();
        for (s, world) in worlds.iter().enumerate() {
            let robot = self
                .robots
                .iter()
                .find(|r| r.site == s)
                .context("every site has a robot")?;
            let (world, sim) = (world.clone(), mapping_sim.clone());
            let recording = tokio::task::spawn_blocking(move || {
                let simulated = world.session(0, &sim)?;
                anyhow::Ok(Arc::new(Recording::from_unsorted(
                    simulated.events,
                    simulated.base_from_laser,
                    ReadReport::default(),
                )))
            })
            .await
            .context("simulator thread")??;
            let mut uploader = Uploader::new(
                robot.uplink.clone(),
                Outbox::in_memory(&site_id(s)),
                &site_id(s),
                &robot.id,
                &format!("load-{}-mapping", robot.id),
            )?;
            let options = SessionOptions {
                replay_speed: 0.0,
                final_flush_timeout: Duration::from_secs(300),
                ..SessionOptions::default()
            };
            mappers.push(tokio::spawn(async move {
                let span = uploader.session_span();
                stream_recording(recording, &options, &mut uploader)
                    .instrument(span)
                    .await
            }));
        }
        for mapper in mappers {
            let report = mapper.await.context("mapping task")??;
            anyhow::ensure!(
                report.left_in_outbox == 0,
                "a mapping session could not deliver everything ({} batches left)",
                report.left_in_outbox
            );
        }
        self.wait_caught_up(worlds.len()).await;
        Ok(())
    }

    /// The current version of every site.
    pub fn site_versions(&self, sites: usize) -> Vec<u64> {
        (0..sites)
            .map(|s| {
                self.server
                    .site(&site_id(s))
                    .map_or(0, |h| h.current().version)
            })
            .collect()
    }

    /// Waits (at most 60 s) until every robot's cache holds its site's current version.
    pub async fn wait_caught_up(&self, sites: usize) {
        let deadline = Instant::now() + Duration::from_secs(60);
        while Instant::now() < deadline {
            let targets = self.site_versions(sites);
            if self
                .robots
                .iter()
                .all(|r| r.cache.lock().is_ok_and(|c| c.version() >= targets[r.site]))
            {
                return;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Stops the followers (and everything watching [`Fleet::stopped`]) and waits for the followers.
    pub async fn stop_following(&mut self) {
        let _ = self.stop.send(true);
        for follower in self.followers.drain(..) {
            let _ = follower.await;
        }
    }
}

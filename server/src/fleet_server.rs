//! Starting and stopping the whole server: site tasks, gRPC (with health and reflection), the optional
//! zenoh front end, and metrics.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use proto::pb::agent_service_server::AgentServiceServer;
use proto::pb::map_service_server::MapServiceServer;
use storage::MapStore;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

use crate::console::RunningConsole;
use crate::grpc::{AgentApi, ApiContext, Auth, MapApi};
use crate::metrics_endpoint::serve_metrics;
use crate::site::{SiteError, SiteHandle, SiteTask, SiteTaskOptions};
use crate::zenoh_front::ZenohFront;
use crate::{ServerConfig, ServerConfigError, ServerMetrics};

/// How long [`RunningServer::shutdown`] waits for open gRPC calls before cutting them.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(5);

/// Why the server could not start or stop cleanly.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The configuration is invalid.
    #[error("invalid configuration: {0}")]
    Config(#[from] ServerConfigError),
    /// A site could not be rebuilt from storage.
    #[error("site {site:?}: {source}")]
    Site {
        /// The site.
        site: String,
        /// Why.
        source: SiteError,
    },
    /// A listener could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// The reflection service could not be built.
    #[error("gRPC reflection: {0}")]
    Reflection(#[source] tonic_reflection::server::Error),
    /// The gRPC server failed.
    #[error("gRPC server: {0}")]
    Transport(#[source] tonic::transport::Error),
    /// The gRPC server's task failed (panicked).
    #[error("gRPC server: {0}")]
    TransportTask(#[source] tokio::task::JoinError),
    /// The TLS certificate or key could not be read.
    #[error("TLS: cannot read {}: {source}", path.display())]
    TlsFile {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The TLS certificate or key could not be used.
    #[error("TLS: {0}")]
    Tls(#[source] tonic::transport::Error),
    /// The zenoh front end could not start.
    #[error(transparent)]
    Zenoh(#[from] crate::zenoh_front::ZenohFrontError),
}

/// How many sites a start loads at once: twice the cores (a load is mostly CPU; the second one per
/// core covers its reads), at least 2.
fn start_parallelism() -> usize {
    std::thread::available_parallelism().map_or(2, |n| n.get().saturating_mul(2).max(2))
}

/// A started server. Stop it with [`RunningServer::shutdown`] (dropping it leaves tasks running until the
/// runtime ends).
pub struct RunningServer {
    grpc_addr: SocketAddr,
    metrics_addr: Option<SocketAddr>,
    sites: Arc<BTreeMap<String, SiteHandle>>,
    site_tasks: Vec<JoinHandle<()>>,
    stop_grpc: oneshot::Sender<()>,
    grpc: JoinHandle<Result<(), tonic::transport::Error>>,
    metrics_task: Option<JoinHandle<()>>,
    metrics: Arc<ServerMetrics>,
    zenoh: Option<ZenohFront>,
    console: Option<RunningConsole>,
}

impl RunningServer {
    /// Validates `config`, rebuilds every configured site from `store`, and starts serving. Sites found in
    /// the store but not configured are left untouched (and not served).
    pub async fn start(
        config: &ServerConfig,
        store: Arc<dyn MapStore>,
    ) -> Result<Self, ServeError> {
        config.validate()?;
        let metrics = Arc::new(ServerMetrics::default());
        // The sites are loaded (each on a blocking thread) a few at a time: a restart takes about the
        // sum of the loads over the cores, and only a few maps are in memory at once besides the sites
        // that stay loaded (with unloading on, a site its checkpoint covers starts unloaded: at most its
        // summary is read, or it is loaded and unloaded again before the next site's turn).
        tracing::info!(sites = config.sites.len(), "replaying the sites' logs");
        let mut loading = tokio::task::JoinSet::new();
        let mut loading_site = BTreeMap::new();
        let turns = Arc::new(tokio::sync::Semaphore::new(start_parallelism()));
        for site in &config.sites {
            let (id, options) = (site.id.clone(), config.map.clone());
            let (store, metrics) = (Arc::clone(&store), Arc::clone(&metrics));
            let task_options = SiteTaskOptions {
                queue_depth: config.site_queue_depth,
                session_idle_timeout: config.session_idle_timeout()?,
                checkpoints: config.checkpoints,
                unload_after: config.site_unload_after()?,
            };
            let turns = Arc::clone(&turns);
            let task = loading.spawn(async move {
                // Never closed: a permit always comes.
                let _turn = turns.acquire_owned().await;
                let loaded = SiteTask::spawn(&id, options, store, metrics, task_options).await;
                (id, loaded)
            });
            loading_site.insert(task.id(), site.id.clone());
        }
        let mut sites = BTreeMap::new();
        let mut site_tasks = Vec::new();
        while let Some(joined) = loading.join_next_with_id().await {
            let (_, (id, loaded)) = joined.map_err(|e| ServeError::Site {
                site: loading_site.get(&e.id()).cloned().unwrap_or_default(),
                source: SiteError::Worker(e),
            })?;
            let (handle, task) = loaded.map_err(|source| ServeError::Site {
                site: id.clone(),
                source,
            })?;
            crate::site::site_span(&id).in_scope(|| {
                tracing::info!(
                    version = handle.current().version,
                    in_memory = handle.is_loaded(),
                    "site loaded"
                );
            });
            sites.insert(id, handle);
            site_tasks.push(task);
        }
        let sites = Arc::new(sites);
        let context = ApiContext {
            sites: Arc::clone(&sites),
            auth: Arc::new(Auth::with_limits(&config.sites, &config.auth)),
            metrics: Arc::clone(&metrics),
            delta_chunk_bytes: config.delta_chunk_bytes,
        };

        let (health, health_service) = tonic_health::server::health_reporter();
        health.set_serving::<AgentServiceServer<AgentApi>>().await;
        health.set_serving::<MapServiceServer<MapApi>>().await;
        let reflection = tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
            .build_v1()
            .map_err(ServeError::Reflection)?;
        let limit = config.max_message_bytes;
        let zenoh = match &config.zenoh {
            Some(options) => {
                Some(ZenohFront::start(options, context.clone(), config.site_queue_depth).await?)
            }
            None => None,
        };
        let agent = AgentServiceServer::new(AgentApi::new(context.clone()))
            .max_decoding_message_size(limit)
            .max_encoding_message_size(limit);
        let map = MapServiceServer::new(MapApi::new(context))
            .max_decoding_message_size(limit)
            .max_encoding_message_size(limit);

        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .map_err(|source| ServeError::Bind {
                addr: config.listen,
                source,
            })?;
        let grpc_addr = listener.local_addr().map_err(|source| ServeError::Bind {
            addr: config.listen,
            source,
        })?;
        let (stop_grpc, stopped) = oneshot::channel::<()>();
        let mut builder = tonic::transport::Server::builder();
        if let Some(tls) = &config.tls {
            let read = |path: &std::path::Path| {
                std::fs::read(path).map_err(|source| ServeError::TlsFile {
                    path: path.to_owned(),
                    source,
                })
            };
            let identity =
                tonic::transport::Identity::from_pem(read(&tls.cert_pem)?, read(&tls.key_pem)?);
            builder = builder
                .tls_config(tonic::transport::ServerTlsConfig::new().identity(identity))
                .map_err(ServeError::Tls)?;
        }
        let grpc = tokio::spawn(
            builder
                .add_service(health_service)
                .add_service(reflection)
                .add_service(agent)
                .add_service(map)
                .serve_with_incoming_shutdown(
                    tokio_stream::wrappers::TcpListenerStream::new(listener),
                    async move {
                        let _ = stopped.await;
                    },
                ),
        );
        tracing::info!(%grpc_addr, sites = sites.len(), tls = config.tls.is_some(), "gRPC serving");

        let (metrics_addr, metrics_task) = match config.metrics_listen {
            Some(addr) => {
                let listener = tokio::net::TcpListener::bind(addr)
                    .await
                    .map_err(|source| ServeError::Bind { addr, source })?;
                let bound = listener
                    .local_addr()
                    .map_err(|source| ServeError::Bind { addr, source })?;
                let handles = Arc::new(sites.values().cloned().collect::<Vec<_>>());
                tracing::info!(metrics_addr = %bound, "metrics serving");
                (
                    Some(bound),
                    Some(tokio::spawn(serve_metrics(
                        listener,
                        Arc::clone(&metrics),
                        handles,
                    ))),
                )
            }
            None => (None, None),
        };
        let console = match &config.http {
            Some(http) => Some(
                RunningConsole::start(http, Arc::clone(&sites), Arc::clone(&metrics))
                    .await
                    .map_err(|source| ServeError::Bind {
                        addr: http.listen,
                        source,
                    })?,
            ),
            None => None,
        };
        Ok(Self {
            grpc_addr,
            metrics_addr,
            sites,
            site_tasks,
            stop_grpc,
            grpc,
            metrics_task,
            metrics,
            zenoh,
            console,
        })
    }

    /// The bound gRPC address (useful with port 0).
    pub fn grpc_addr(&self) -> SocketAddr {
        self.grpc_addr
    }

    /// The bound metrics address, if enabled.
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_addr
    }

    /// The bound address of the web console, if enabled.
    pub fn console_addr(&self) -> Option<SocketAddr> {
        self.console.as_ref().map(RunningConsole::addr)
    }

    /// A site's handle (for in-process front ends and tests).
    pub fn site(&self, id: &str) -> Option<&SiteHandle> {
        self.sites.get(id)
    }

    /// The server's counters.
    pub fn metrics(&self) -> &Arc<ServerMetrics> {
        &self.metrics
    }

    /// Stops the web console, then the site tasks (ending watch streams), then the zenoh front end, then the gRPC server (waiting up to 5 s for open
    /// calls), then the metrics endpoint. Everything acknowledged is already durable.
    pub async fn shutdown(self) -> Result<(), ServeError> {
        if let Some(console) = self.console {
            console.shutdown().await;
        }
        for site in self.sites.values() {
            site.shutdown().await;
        }
        for task in self.site_tasks {
            let _ = task.await;
        }
        if let Some(zenoh) = self.zenoh {
            zenoh.shutdown().await;
        }
        let _ = self.stop_grpc.send(());
        let mut grpc = self.grpc;
        let result = match tokio::time::timeout(SHUTDOWN_GRACE, &mut grpc).await {
            Ok(Ok(Ok(()))) => Ok(()),
            Ok(Ok(Err(e))) => Err(ServeError::Transport(e)),
            Ok(Err(e)) => Err(ServeError::TransportTask(e)),
            Err(_) => {
                tracing::warn!("gRPC calls still open after the grace period: cutting them");
                grpc.abort();
                let _ = grpc.await;
                Ok(())
            }
        };
        if let Some(task) = self.metrics_task {
            task.abort();
            let _ = task.await;
        }
        tracing::info!("server stopped");
        result
    }
}

#[cfg(test)]
mod tests {
    use storage::{MemStore, RecordId, WriteBatch};

    use super::*;
    use crate::site::SITE_LOG_KIND;
    use crate::{RobotConfig, SiteConfig};

    fn site(id: &str) -> SiteConfig {
        SiteConfig {
            id: id.into(),
            robots: vec![RobotConfig {
                id: "robot".into(),
                token: format!("token-of-{id}"),
            }],
        }
    }

    #[tokio::test]
    async fn a_site_whose_log_cannot_be_replayed_stops_the_start_and_is_named() {
        let store = Arc::new(MemStore::new());
        // "bad"'s first log entry is not a log entry.
        let mut batch = WriteBatch::new("bad");
        batch
            .put(SITE_LOG_KIND, RecordId::from_u64(1), vec![0xff; 7])
            .bump_map_version();
        store.apply(&batch).unwrap();
        let config = ServerConfig {
            listen: "127.0.0.1:0".parse().unwrap(),
            metrics_listen: None,
            sites: ["good-1", "bad", "good-2"].map(site).to_vec(),
            ..ServerConfig::default()
        };
        let started = RunningServer::start(&config, store).await;
        match started {
            Err(ServeError::Site { site, source }) => {
                assert_eq!(site, "bad");
                assert!(
                    matches!(source, SiteError::CorruptEntry { index: 1, .. }),
                    "{source}"
                );
            }
            Err(other) => panic!("the wrong error: {other}"),
            Ok(_) => panic!("a site whose log cannot be replayed must stop the start"),
        }
    }
}

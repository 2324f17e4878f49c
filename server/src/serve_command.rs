//! `evermap-server serve`: the fleet map server on a sled store until Ctrl-C or SIGTERM (how service
//! managers stop it), either of which shuts it down gracefully.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Context as _;
use server::{RunningServer, ServerConfig};
use storage::SledStore;
use tracing_subscriber::filter::LevelFilter;

/// Arguments of `serve`.
#[derive(clap::Args)]
pub struct ServeArgs {
    /// TOML configuration (see `server_config.rs` for every key); defaults apply without it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Log more (debug level); `RUST_LOG`, when set, decides instead.
    #[arg(long, short)]
    verbose: bool,
}

impl ServeArgs {
    /// The log level without `RUST_LOG`: INFO, or DEBUG with `--verbose`.
    pub fn log_level(&self) -> LevelFilter {
        if self.verbose {
            LevelFilter::DEBUG
        } else {
            LevelFilter::INFO
        }
    }
}

/// Runs the command (the caller has set up logging: [`server::init_logging`]).
pub fn run(args: &ServeArgs) -> anyhow::Result<()> {
    let config = read_config(args.config.as_deref())?;
    if config.sites.is_empty() {
        tracing::warn!("no sites configured: nothing can be uploaded");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("evermap-server")
        .build()?;
    runtime.block_on(async {
        let store_options = config.storage.clone();
        let store = tokio::task::spawn_blocking(move || SledStore::open(&store_options))
            .await?
            .with_context(|| format!("cannot open storage at {}", config.storage.path.display()))?;
        let server = RunningServer::start(&config, Arc::new(store)).await?;
        let signal = stop_signal().await?;
        tracing::info!("{signal}: shutting down");
        server.shutdown().await?;
        anyhow::Ok(())
    })
}

/// The configuration in `path` (TOML), or the defaults without one, validated.
pub fn read_config(path: Option<&Path>) -> anyhow::Result<ServerConfig> {
    let config = match path {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("cannot read {}", path.display()))?;
            ServerConfig::from_toml(&text).with_context(|| format!("in {}", path.display()))?
        }
        None => ServerConfig::default(),
    };
    config.validate()?;
    Ok(config)
}

/// Waits for Ctrl-C (SIGINT) or, on Unix, SIGTERM; returns which came.
async fn stop_signal() -> anyhow::Result<&'static str> {
    #[cfg(unix)]
    {
        let mut terminate =
            tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        tokio::select! {
            result = tokio::signal::ctrl_c() => result.map(|()| "Ctrl-C").map_err(Into::into),
            _ = terminate.recv() => Ok("SIGTERM"),
        }
    }
    #[cfg(not(unix))]
    {
        tokio::signal::ctrl_c().await?;
        Ok("Ctrl-C")
    }
}

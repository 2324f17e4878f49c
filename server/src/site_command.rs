//! `evermap-server site`: a stopped instance's sites, for moving a site to another instance (ARCHITECTURE.md
//! "Scaling out to many stores"): `list`, `export` to an archive file, `import` from one, `delete`.
//!
//! Each command opens the store the instance's configuration names (`[storage] path`), which the instance
//! must not be serving: sled locks its directory, and a locked store is refused with that advice rather
//! than waited for. The move of site S from instance A to instance B, each stopped once:
//!
//! ```text
//! stop A;  evermap-server site export --config a.toml --site S --out S.evermap-site
//! stop B;  evermap-server site import --config b.toml --site S --archive S.evermap-site   (b.toml lists S)
//! start B; evermap-server site delete --config a.toml --site S --yes                      (a.toml no longer lists S)
//! start A
//! ```
//!
//! The archive carries the map version and every session's last sequence number, so B continues A's
//! versions and the robots' outboxes resume exactly once; they hold their batches while nobody serves S.

use std::fs::File;
use std::io::{BufReader, BufWriter, Write as _};
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use server::ServerConfig;
use storage::{MapStore as _, SledStore, SledStoreOptions, StorageError};

use crate::serve_command::read_config;

/// Arguments of `site`.
#[derive(clap::Args)]
pub struct SiteArgs {
    #[command(subcommand)]
    command: SiteCommand,
}

#[derive(clap::Subcommand)]
enum SiteCommand {
    /// Lists the sites in the store, their map versions, and whether the configuration serves them.
    List(StoreArgs),
    /// Writes one site of the store to an archive file (written whole, then renamed into place).
    Export {
        #[command(flatten)]
        store: StoreArgs,
        /// The site to export.
        #[arg(long)]
        site: String,
        /// The archive file to write; refused if it exists.
        #[arg(long)]
        out: PathBuf,
    },
    /// Reads a site archive into the store; refused if the store already holds the site.
    Import {
        #[command(flatten)]
        store: StoreArgs,
        /// The site id to import as (usually the id it had).
        #[arg(long)]
        site: String,
        /// The archive file, as `export` wrote it.
        #[arg(long)]
        archive: PathBuf,
    },
    /// Removes a site and all its data from the store; refused while the configuration still lists it.
    Delete {
        #[command(flatten)]
        store: StoreArgs,
        /// The site to delete.
        #[arg(long)]
        site: String,
        /// Confirms the deletion: it is permanent (export the site first).
        #[arg(long)]
        yes: bool,
    },
}

/// The instance whose store a command opens.
#[derive(clap::Args)]
struct StoreArgs {
    /// The instance's TOML configuration (its `[storage] path` and `[[sites]]`); defaults without it.
    #[arg(long)]
    config: Option<PathBuf>,
}

impl StoreArgs {
    fn config(&self) -> anyhow::Result<ServerConfig> {
        read_config(self.config.as_deref())
    }
}

pub fn run(args: &SiteArgs) -> anyhow::Result<()> {
    match &args.command {
        SiteCommand::List(store) => list(&store.config()?),
        SiteCommand::Export { store, site, out } => export(&store.config()?, site, out),
        SiteCommand::Import {
            store,
            site,
            archive,
        } => import(&store.config()?, site, archive),
        SiteCommand::Delete { store, site, yes } => delete(&store.config()?, site, *yes),
    }
}

fn serves(config: &ServerConfig, site: &str) -> bool {
    config.sites.iter().any(|s| s.id == site)
}

/// Opens the configured store; `must_exist`: refuse a path that holds no store rather than create one.
fn open_store(config: &ServerConfig, must_exist: bool) -> anyhow::Result<SledStore> {
    let path = &config.storage.path;
    if must_exist && !path.exists() {
        anyhow::bail!("no store at {}: check [storage] path", path.display());
    }
    // A serving instance holds the lock for as long as it runs: fail at once, not after retries.
    let options = SledStoreOptions {
        open_attempts: 1,
        ..config.storage.clone()
    };
    SledStore::open(&options).map_err(|error| match error {
        StorageError::Locked { .. } => anyhow::anyhow!(
            "the store at {} is in use (is an evermap-server still serving it? stop it first)",
            path.display()
        ),
        other => anyhow::Error::new(other).context(format!("cannot open {}", path.display())),
    })
}

/// Opens the configured store, which must hold `site`; the store and the site's map version.
fn open_stored_site(config: &ServerConfig, site: &str) -> anyhow::Result<(SledStore, u64)> {
    let store = open_store(config, true)?;
    anyhow::ensure!(
        store.list_sites()?.iter().any(|s| s == site),
        "the store at {} holds no site {site:?}",
        config.storage.path.display()
    );
    let version = store.map_version(site)?;
    Ok((store, version))
}

fn list(config: &ServerConfig) -> anyhow::Result<()> {
    let store = open_store(config, true)?;
    let stored = store.list_sites()?;
    for site in &stored {
        println!(
            "{site}\tversion {}\t{}",
            store.map_version(site)?,
            if serves(config, site) {
                "served by this configuration"
            } else {
                "not in this configuration's [[sites]]"
            }
        );
    }
    for site in config.sites.iter().filter(|s| !stored.contains(&s.id)) {
        println!("{}\tversion 0\tconfigured, no data yet", site.id);
    }
    Ok(())
}

fn export(config: &ServerConfig, site: &str, out: &Path) -> anyhow::Result<()> {
    anyhow::ensure!(
        !out.exists(),
        "{} exists: refusing to overwrite it",
        out.display()
    );
    let (store, version) = open_stored_site(config, site)?;
    // Written whole beside the target, then renamed: a crash never leaves a truncated archive under the
    // name an import would read.
    let partial = partial_path(out);
    let written = write_archive(&store, site, &partial).and_then(|summary| {
        std::fs::rename(&partial, out)
            .with_context(|| format!("cannot rename {} to {}", partial.display(), out.display()))?;
        sync_parent(out)?;
        Ok(summary)
    });
    // A half-written archive is of no use to anyone.
    let summary = written.inspect_err(|_| {
        let _ = std::fs::remove_file(&partial);
    })?;
    println!(
        "exported {site} at version {version}: {} records, {} payload bytes, to {}",
        summary.records,
        summary.payload_bytes,
        out.display()
    );
    if serves(config, site) {
        println!(
            "note: this configuration still serves {site}; remove it from [[sites]] before this instance starts again"
        );
    }
    Ok(())
}

fn import(config: &ServerConfig, site: &str, archive: &Path) -> anyhow::Result<()> {
    let file = File::open(archive).with_context(|| format!("cannot open {}", archive.display()))?;
    let store = open_store(config, false)?;
    let summary = store
        .import_site(site, &mut BufReader::new(file))
        .with_context(|| format!("importing {} as {site}", archive.display()))?;
    println!(
        "imported {site} at version {}: {} records, {} payload bytes, into {}",
        store.map_version(site)?,
        summary.records,
        summary.payload_bytes,
        config.storage.path.display()
    );
    if !serves(config, site) {
        println!(
            "note: this configuration does not serve {site}; add it to [[sites]] (with its robots) before starting"
        );
    }
    Ok(())
}

fn delete(config: &ServerConfig, site: &str, yes: bool) -> anyhow::Result<()> {
    anyhow::ensure!(
        !serves(config, site),
        "this configuration still serves {site}: remove it from [[sites]] first (the instance would \
         serve it empty)"
    );
    anyhow::ensure!(
        yes,
        "deleting {site} is permanent: export it first, then pass --yes"
    );
    let (store, version) = open_stored_site(config, site)?;
    store.delete_site(site)?;
    println!(
        "deleted {site} (it was at version {version}) from {}",
        config.storage.path.display()
    );
    Ok(())
}

/// Writes `site` of `store` to the archive file `path`, synced to disk.
fn write_archive(
    store: &SledStore,
    site: &str,
    path: &Path,
) -> anyhow::Result<storage::TransferSummary> {
    let file = File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut writer = BufWriter::new(file);
    let summary = store
        .export_site(site, &mut writer)
        .with_context(|| format!("exporting {site}"))?;
    writer.flush()?;
    writer
        .into_inner()
        .map_err(std::io::IntoInnerError::into_error)?
        .sync_all()
        .with_context(|| format!("cannot sync {}", path.display()))?;
    Ok(summary)
}

/// `out` with `.partial` appended to its file name.
fn partial_path(out: &Path) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(".partial");
    out.with_file_name(name)
}

/// Makes a rename in `path`'s directory durable.
fn sync_parent(path: &Path) -> anyhow::Result<()> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    File::open(parent)
        .and_then(|dir| dir.sync_all())
        .with_context(|| format!("cannot sync {}", parent.display()))
}

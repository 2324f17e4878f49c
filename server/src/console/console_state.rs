//! What the console's routes share: the sites, the token, the rendered-image caches, when each version
//! landed, and the broadcast of new versions that feeds the event streams.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{SystemTime, UNIX_EPOCH};

use serde::Serialize;
use tokio::sync::broadcast;
use tokio::task::JoinHandle;

use super::console_auth::ConsoleAuth;
use super::http_config::HttpConfig;
use super::map_images::{ChangeImage, MapImage, render_map_image};
use crate::ServerMetrics;
use crate::site::{HistoryEntry, MapCounts, SiteHandle};

/// A map image being rendered or rendered (`None`: nothing to draw), shared by every request for it.
type MapSlot = tokio::sync::OnceCell<Option<Arc<MapImage>>>;

/// Versions whose landing time is remembered per site, count.
const LANDED_KEPT: usize = 4096;
/// Rendered images kept (per kind), count.
const IMAGES_KEPT: usize = 24;
/// Version events buffered for a slow event stream before it skips some, count.
const EVENTS_BUFFERED: usize = 256;

/// A new site version, as sent on the event stream.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct VersionEvent {
    /// The site.
    pub site: String,
    /// Its new version.
    pub version: u64,
    /// When the console saw it published, milliseconds since the Unix epoch.
    pub landed_at_ms: u64,
    /// Sessions opened and not ended.
    pub open_sessions: u64,
}

/// A site's map leaving memory (idle) or coming back, as sent on the event stream (`site`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct LoadEvent {
    /// The site.
    pub site: String,
    /// Whether its map is in memory now.
    pub loaded: bool,
}

/// A small cache of the newest-used rendered images.
struct ImageCache<K, V> {
    entries: VecDeque<(K, Arc<V>)>,
}

impl<K: PartialEq, V> ImageCache<K, V> {
    fn get(&mut self, key: &K) -> Option<Arc<V>> {
        let i = self.entries.iter().position(|(k, _)| k == key)?;
        let entry = self.entries.remove(i)?;
        let value = Arc::clone(&entry.1);
        self.entries.push_back(entry);
        Some(value)
    }

    fn put(&mut self, key: K, value: Arc<V>) {
        self.entries.retain(|(k, _)| *k != key);
        if self.entries.len() >= IMAGES_KEPT {
            self.entries.pop_front();
        }
        self.entries.push_back((key, value));
    }
}

/// Everything the console's routes share. Thread-safe.
pub struct ConsoleState {
    /// The sites, by id.
    pub sites: Arc<BTreeMap<String, SiteHandle>>,
    /// The operator token check.
    pub auth: ConsoleAuth,
    /// The server's counters (`/metrics`).
    pub metrics: Arc<ServerMetrics>,
    /// Cell size of the rendered images, m.
    pub resolution: f64,
    events: broadcast::Sender<VersionEvent>,
    loads: broadcast::Sender<LoadEvent>,
    landed: Mutex<BTreeMap<String, VecDeque<(u64, u64)>>>,
    maps: Mutex<ImageCache<(String, u64), MapSlot>>,
    changes: Mutex<ImageCache<(String, u64, u64), ChangeImage>>,
}

/// Milliseconds since the Unix epoch, now.
pub fn unix_ms_now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

impl ConsoleState {
    /// The state of a console over `sites`.
    pub fn new(
        config: &HttpConfig,
        sites: Arc<BTreeMap<String, SiteHandle>>,
        metrics: Arc<ServerMetrics>,
    ) -> Self {
        let (events, _) = broadcast::channel(EVENTS_BUFFERED);
        let (loads, _) = broadcast::channel(EVENTS_BUFFERED);
        Self {
            sites,
            auth: ConsoleAuth::new(config.operator_token.clone()),
            metrics,
            resolution: config.map_resolution_m,
            events,
            loads,
            landed: Mutex::new(BTreeMap::new()),
            maps: Mutex::new(ImageCache {
                entries: VecDeque::new(),
            }),
            changes: Mutex::new(ImageCache {
                entries: VecDeque::new(),
            }),
        }
    }

    /// Starts, per site, a task that notes when each new version lands and broadcasts it, one that
    /// renders the newest map as soon as it lands while a page follows the events (one render at a time
    /// per site, always of the newest map; requests for it share that render), and one that broadcasts
    /// the site's map leaving memory or coming back. The tasks end when their site stops.
    pub fn watch_versions(self: &Arc<Self>) -> Vec<JoinHandle<()>> {
        let mut tasks = Vec::new();
        for site in self.sites.values() {
            let (state, mut versions) = (Arc::clone(self), site.subscribe());
            let id = site.site().to_owned();
            // The current version is marked seen here, not in the task: there it would swallow a version
            // that landed before the task first ran.
            versions.borrow_and_update();
            tasks.push(tokio::spawn(async move {
                // Ends when the site's task stops (the sender is dropped).
                while versions.changed().await.is_ok() {
                    let info = *versions.borrow_and_update();
                    state.landed(&id, info.version, info.counts);
                }
            }));
            let (state, mut versions, handle) = (Arc::clone(self), site.subscribe(), site.clone());
            tasks.push(tokio::spawn(async move {
                while versions.changed().await.is_ok() {
                    versions.borrow_and_update();
                    if state.events.receiver_count() == 0 {
                        continue;
                    }
                    if let Some(entry) = handle.map_at(u64::MAX) {
                        let _ = state.map_image(handle.site(), entry).await;
                    }
                }
            }));
            let (state, mut views) = (Arc::clone(self), site.subscribe_views());
            let id = site.site().to_owned();
            let mut loaded = !views.borrow_and_update().unloaded;
            tasks.push(tokio::spawn(async move {
                while views.changed().await.is_ok() {
                    let now = !views.borrow_and_update().unloaded;
                    if now != loaded {
                        loaded = now;
                        // No subscriber is not an error.
                        let _ = state.loads.send(LoadEvent {
                            site: id.clone(),
                            loaded,
                        });
                    }
                }
            }));
        }
        tasks
    }

    /// The map image of `entry` (a history entry of `site`): rendered on the blocking pool once, then
    /// cached; concurrent requests share one render. `None` when there is nothing to draw.
    pub async fn map_image(&self, site: &str, entry: HistoryEntry) -> Option<Arc<MapImage>> {
        let slot = {
            let mut maps = self.maps.lock().ok()?;
            let key = (site.to_owned(), entry.version);
            maps.get(&key).unwrap_or_else(|| {
                let slot = Arc::new(MapSlot::new());
                maps.put(key, Arc::clone(&slot));
                slot
            })
        };
        let resolution = self.resolution;
        slot.get_or_init(|| async move {
            tokio::task::spawn_blocking(move || render_map_image(&entry, resolution))
                .await
                .ok()
                .flatten()
                .map(Arc::new)
        })
        .await
        .clone()
    }

    /// Notes that `site` published `version` now and tells the event streams.
    pub fn landed(&self, site: &str, version: u64, counts: MapCounts) {
        let now = unix_ms_now();
        if let Ok(mut landed) = self.landed.lock() {
            let times = landed.entry(site.to_owned()).or_default();
            if times.len() >= LANDED_KEPT {
                times.pop_front();
            }
            times.push_back((version, now));
        }
        // No subscriber is not an error.
        let _ = self.events.send(VersionEvent {
            site: site.to_owned(),
            version,
            landed_at_ms: now,
            open_sessions: counts.open_sessions,
        });
    }

    /// When `site`'s `version` landed (ms since the Unix epoch), if the console saw it.
    pub fn landed_at(&self, site: &str, version: u64) -> Option<u64> {
        let landed = self.landed.lock().ok()?;
        let times = landed.get(site)?;
        let i = times.partition_point(|(v, _)| *v < version);
        times
            .get(i)
            .filter(|(v, _)| *v == version)
            .map(|(_, at)| *at)
    }

    /// A receiver of every version landing from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<VersionEvent> {
        self.events.subscribe()
    }

    /// A receiver of every site's map leaving memory or coming back from now on.
    pub fn subscribe_loads(&self) -> broadcast::Receiver<LoadEvent> {
        self.loads.subscribe()
    }

    /// The site's handle.
    pub fn site(&self, site: &str) -> Result<&SiteHandle, super::ConsoleError> {
        self.sites
            .get(site)
            .ok_or_else(|| super::ConsoleError::UnknownSite(site.to_owned()))
    }

    /// A cached change image of `site` between map versions `from` and `to`.
    pub fn cached_change(&self, site: &str, from: u64, to: u64) -> Option<Arc<ChangeImage>> {
        self.changes.lock().ok()?.get(&(site.to_owned(), from, to))
    }

    /// Caches a change image.
    pub fn cache_change(&self, site: &str, image: Arc<ChangeImage>) {
        if let Ok(mut changes) = self.changes.lock() {
            changes.put(
                (
                    site.to_owned(),
                    image.from_map_version,
                    image.to_map_version,
                ),
                image,
            );
        }
    }
}

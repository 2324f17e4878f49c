//! Hostile input that reaches a running site: zenoh request payloads answered by the server's own handlers
//! (`server::zenoh_front::answer`: decode, version and token checks, the gRPC handlers, the site task),
//! upload batches inside valid requests (so they reach the site map), and
//! site archives imported into a store and replayed into a site map (`storage` chunk framing and CRCs,
//! record envelopes, then the server's decoding of every stored `SiteLogEntry`).
//!
//! Both run on one in-memory site, `store-1` (token `change-me-robot-1`), on a current-thread tokio runtime.

use std::collections::BTreeMap;
use std::sync::Arc;

use mapping::lifelong::LifelongOptions;
use prost::Message as _;
use proto::{FORMAT_VERSION, pb};
use server::grpc::{AgentApi, ApiContext, Auth, MapApi};
use server::site::{SiteHandle, SiteTask, SiteTaskOptions};
use server::{RobotConfig, ServerMetrics, SiteConfig};
use storage::{MapStore, MemStore, RecordKind};
use tokio::runtime::Runtime;
use tokio::task::JoinHandle;

use super::super::fuzz_target::{FuzzTarget, Verdict};
use super::SetupError;
use super::protobuf::sample_upload_batch;

const SITE: &str = "store-1";
const ROBOT: &str = "robot-1";
const TOKEN: &str = "change-me-robot-1";
const SESSION: &str = "4f1c2a9e-0000-4000-8000-000000000001";
/// Inputs answered by one site before it is rebuilt (bounds what accepted uploads accumulate).
const INPUTS_PER_SITE: u32 = 200;

fn setup_error(reason: String) -> SetupError {
    SetupError::Seed {
        path: "<in-memory site>".into(),
        reason,
    }
}

fn runtime() -> Result<Runtime, SetupError> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| setup_error(e.to_string()))
}

/// One site served by the real handlers over a `MemStore`.
struct Site {
    agent: AgentApi,
    map: MapApi,
    handle: SiteHandle,
    task: JoinHandle<()>,
}

impl Site {
    async fn start(store: Arc<dyn MapStore>) -> Result<Self, String> {
        let metrics = Arc::new(ServerMetrics::default());
        let (handle, task) = SiteTask::spawn(
            SITE,
            LifelongOptions::default(),
            Arc::clone(&store),
            Arc::clone(&metrics),
            SiteTaskOptions {
                queue_depth: 4,
                session_idle_timeout: None,
                ..SiteTaskOptions::default()
            },
        )
        .await
        .map_err(|e| e.to_string())?;
        let sites = Arc::new(BTreeMap::from([(SITE.to_owned(), handle.clone())]));
        let context = ApiContext {
            sites,
            auth: Arc::new(Auth::from_sites(&[SiteConfig {
                id: SITE.into(),
                robots: vec![RobotConfig {
                    id: ROBOT.into(),
                    token: TOKEN.into(),
                }],
            }])),
            metrics,
            delta_chunk_bytes: 1 << 20,
        };
        Ok(Self {
            agent: AgentApi::new(context.clone()),
            map: MapApi::new(context),
            handle,
            task,
        })
    }

    async fn stop(self) {
        drop(self.agent);
        drop(self.map);
        drop(self.handle);
        self.task.abort();
        let _ = self.task.await;
    }
}

fn request(request: pb::zenoh_request::Request) -> Vec<u8> {
    pb::ZenohRequest {
        format_version: FORMAT_VERSION,
        token: TOKEN.into(),
        request: Some(request),
    }
    .encode_to_vec()
}

/// A session's requests as a robot sends them: open, two uploads, reads, close.
fn session_requests() -> Vec<Vec<u8>> {
    use pb::zenoh_request::Request;
    let mut first = pb::UploadBatch::from(&sample_upload_batch());
    first.site = SITE.into();
    first.robot_id = ROBOT.into();
    first.session_uuid = SESSION.into();
    first.seq = 1;
    // The session ends in its own batch.
    let end = first.items.pop();
    let mut second = first.clone();
    second.seq = 2;
    second.items = end.into_iter().collect();
    vec![
        request(Request::OpenSession(pb::OpenSessionRequest {
            format_version: FORMAT_VERSION,
            site: SITE.into(),
            robot_id: ROBOT.into(),
            session_uuid: SESSION.into(),
        })),
        request(Request::Upload(first)),
        request(Request::GetVersion(pb::GetVersionRequest {
            site: SITE.into(),
        })),
        request(Request::Upload(second)),
        request(Request::GetDelta(pb::GetDeltaRequest {
            site: SITE.into(),
            since_version: 0,
        })),
        request(Request::CloseSession(pb::CloseSessionRequest {
            format_version: FORMAT_VERSION,
            site: SITE.into(),
            robot_id: ROBOT.into(),
            session_uuid: SESSION.into(),
        })),
    ]
}

/// What the server answered: `Accepted` unless the only reply is a refusal.
fn verdict(replies: &[pb::ZenohReply]) -> Verdict {
    assert!(!replies.is_empty(), "invariant: a query got no reply");
    for reply in replies {
        assert_eq!(
            reply.format_version, FORMAT_VERSION,
            "invariant: reply without our format version"
        );
    }
    match replies.first().and_then(|r| r.reply.as_ref()) {
        Some(pb::zenoh_reply::Reply::Error(status)) => {
            // Bad input is refused with a reason; an internal error means the server itself broke.
            assert_ne!(
                status.code,
                tonic::Code::Internal as i32,
                "invariant: the server failed internally: {}",
                status.message
            );
            Verdict::Rejected(status.message.clone())
        }
        Some(_) => Verdict::Accepted,
        None => panic!("invariant: an empty reply"),
    }
}

/// Zenoh request payloads answered by the server's handlers.
pub fn zenoh_requests() -> Result<FuzzTarget, SetupError> {
    let runtime = runtime()?;
    let seeds = session_requests();
    let mut site: Option<Site> = None;
    let mut answered = 0_u32;
    Ok(FuzzTarget::new(
        "zenoh_request",
        "zenoh query payloads through server::zenoh_front::answer (handlers, site task)",
        seeds,
        false,
        Box::new(move |input| {
            runtime.block_on(async {
                if answered >= INPUTS_PER_SITE
                    && let Some(old) = site.take()
                {
                    old.stop().await;
                }
                if site.is_none() {
                    answered = 0;
                    let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
                    site = Some(
                        Site::start(store)
                            .await
                            .unwrap_or_else(|e| panic!("setup: cannot start the site: {e}")),
                    );
                }
                answered += 1;
                let Some(running) = site.as_ref() else {
                    return Verdict::Rejected("no site".into());
                };
                let replies =
                    server::zenoh_front::answer(&running.agent, &running.map, Some(input)).await;
                verdict(&replies)
            })
        }),
    ))
}

/// Upload batches (prost bytes) that reach the site map: each input opens a fresh session, then its
/// batch is sent in a valid `ZenohRequest` with the site, robot, session and sequence number set right, so
/// the mutations land in the items (nodes, points, submap grids, priors, matches) the site map applies.
pub fn zenoh_uploads() -> Result<FuzzTarget, SetupError> {
    let runtime = runtime()?;
    let batch = pb::UploadBatch::from(&sample_upload_batch());
    let mut node_only = batch.clone();
    node_only.items.truncate(2);
    let seeds = vec![batch.encode_to_vec(), node_only.encode_to_vec()];
    let mut site: Option<Site> = None;
    let mut sessions = 0_u32;
    let mut target = FuzzTarget::new(
        "zenoh_upload",
        "upload batches applied by a site map (fresh session per input, valid envelope)",
        seeds,
        false,
        Box::new(move |input| {
            use pb::zenoh_request::Request;
            let mut batch = match pb::UploadBatch::decode(input) {
                Ok(batch) => batch,
                Err(e) => return Verdict::Rejected(e.to_string()),
            };
            runtime.block_on(async {
                if sessions >= INPUTS_PER_SITE / 2
                    && let Some(old) = site.take()
                {
                    old.stop().await;
                }
                if site.is_none() {
                    sessions = 0;
                    let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
                    site = Some(
                        Site::start(store)
                            .await
                            .unwrap_or_else(|e| panic!("setup: cannot start the site: {e}")),
                    );
                }
                sessions += 1;
                let Some(running) = site.as_ref() else {
                    return Verdict::Rejected("no site".into());
                };
                let session = format!("fuzz-session-{sessions}");
                let open = request(Request::OpenSession(pb::OpenSessionRequest {
                    format_version: FORMAT_VERSION,
                    site: SITE.into(),
                    robot_id: ROBOT.into(),
                    session_uuid: session.clone(),
                }));
                let opened =
                    server::zenoh_front::answer(&running.agent, &running.map, Some(&open)).await;
                if let Verdict::Rejected(reason) = verdict(&opened) {
                    panic!("setup: a fresh session was refused: {reason}");
                }
                batch.format_version = FORMAT_VERSION;
                batch.site = SITE.into();
                batch.robot_id = ROBOT.into();
                batch.session_uuid = session;
                batch.seq = 1;
                let upload = request(Request::Upload(batch));
                let result = verdict(
                    &server::zenoh_front::answer(&running.agent, &running.map, Some(&upload)).await,
                );
                // The site task may still be working on what the batch started (optimization, trimming):
                // a probe queued behind it fails here, on this input, if that work killed the site map.
                let probe = request(Request::OpenSession(pb::OpenSessionRequest {
                    format_version: FORMAT_VERSION,
                    site: SITE.into(),
                    robot_id: ROBOT.into(),
                    session_uuid: format!("fuzz-probe-{sessions}"),
                }));
                verdict(
                    &server::zenoh_front::answer(&running.agent, &running.map, Some(&probe)).await,
                );
                result
            })
        }),
    );
    // A batch's grids are zlib-compressed (1032:1 at most).
    target.heap_per_input_byte = 1100;
    Ok(target)
}

/// Exports the site a robot's session leaves behind (open, two uploads, close), as an archive.
fn session_archive(runtime: &Runtime) -> Result<Vec<u8>, SetupError> {
    runtime.block_on(async {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let site = Site::start(Arc::clone(&store)).await.map_err(setup_error)?;
        for payload in session_requests() {
            let replies = server::zenoh_front::answer(&site.agent, &site.map, Some(&payload)).await;
            if let Verdict::Rejected(reason) = verdict(&replies) {
                return Err(setup_error(format!(
                    "the seed session was refused: {reason}"
                )));
            }
        }
        site.stop().await;
        let mut archive = Vec::new();
        store
            .export_site(SITE, &mut archive)
            .map_err(|e| setup_error(e.to_string()))?;
        Ok(archive)
    })
}

/// Recomputes the CRC of every chunk whose length still fits, so mutations reach the chunk bodies (record
/// framing and the stored `SiteLogEntry` payloads) instead of stopping at the checksum.
fn fix_archive_crcs(bytes: &mut [u8]) {
    let mut pos = 10; // magic (8) + version (2)
    while pos + 8 <= bytes.len() {
        let len = u32::from_le_bytes([bytes[pos], bytes[pos + 1], bytes[pos + 2], bytes[pos + 3]])
            as usize;
        let Some(body) = bytes.get(pos + 8..pos + 8 + len) else {
            return;
        };
        let crc = crc32fast::hash(body);
        bytes[pos + 4..pos + 8].copy_from_slice(&crc.to_le_bytes());
        pos += 8 + len;
    }
}

/// Site archives: imported into an empty store, then replayed into a site map as the server does at start.
pub fn site_archive() -> Result<FuzzTarget, SetupError> {
    let runtime = runtime()?;
    let seeds = vec![session_archive(&runtime)?];
    let mut target = FuzzTarget::new(
        "site_archive",
        "site archives (storage import: framing, CRCs, envelopes) replayed into a site map",
        seeds,
        false,
        Box::new(move |input| {
            let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
            let imported = store.import_site(SITE, &mut &input[..]);
            if let Err(e) = imported {
                assert!(
                    store.list_sites().is_ok_and(|sites| sites.is_empty()),
                    "invariant: a refused import left a listed site"
                );
                return Verdict::Rejected(e.to_string());
            }
            for kind in RecordKind::ALL {
                let scanned = store
                    .scan(SITE, kind)
                    .unwrap_or_else(|e| panic!("invariant: cannot scan what was imported: {e}"));
                for record in scanned {
                    record.unwrap_or_else(|e| {
                        panic!("invariant: cannot read back an imported {kind} record: {e}")
                    });
                }
            }
            runtime.block_on(async {
                match Site::start(store).await {
                    Ok(site) => {
                        site.stop().await;
                        Verdict::Accepted
                    }
                    Err(e) => Verdict::Rejected(format!("replay: {e}")),
                }
            })
        }),
    );
    target.fixup = Some(fix_archive_crcs);
    Ok(target)
}

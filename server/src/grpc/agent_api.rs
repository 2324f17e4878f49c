//! `AgentService`: sessions and uploads from robots.

use prost::Message as _;
use proto::{FORMAT_VERSION, UploadBatch, pb};
use tonic::{Request, Response, Status};
use tracing::Instrument as _;

use super::{ApiContext, status};

/// The `AgentService` implementation.
#[derive(Clone)]
pub struct AgentApi {
    context: ApiContext,
}

impl AgentApi {
    /// Serves the context's sites.
    pub fn new(context: ApiContext) -> Self {
        Self { context }
    }
}

fn check_robot(context: &ApiContext, granted: &str, asked: &str) -> Result<(), Status> {
    if granted == asked {
        Ok(())
    } else {
        Err(status::counted(
            &context.metrics,
            Status::permission_denied(format!(
                "this token belongs to robot {granted:?}, not {asked:?}"
            )),
        ))
    }
}

// Each request is served in a span named after its RPC, with the site, robot and session it asks
// for, so its lines (the refusals logged for it included) name them. At ERROR level, as the site
// task's spans: a filter at WARN still shows whose request a warning is about.
#[tonic::async_trait]
impl pb::agent_service_server::AgentService for AgentApi {
    async fn open_session(
        &self,
        request: Request<pb::OpenSessionRequest>,
    ) -> Result<Response<pb::OpenSessionResponse>, Status> {
        let r = request.get_ref();
        let span = tracing::error_span!(
            "open_session", site = %r.site, robot = %r.robot_id, session = %r.session_uuid
        );
        async {
            let c = &self.context;
            c.metrics.add_bytes_in(r.encoded_len());
            proto::check_format_version("OpenSessionRequest", r.format_version)
                .map_err(|e| status::from_conversion(&c.metrics, &e))?;
            let (grant, site) = c.site(&request, &r.site)?;
            check_robot(c, &grant.robot_id, &r.robot_id)?;
            let (opened, map_version) = site
                .open_session(&r.robot_id, &r.session_uuid)
                .await
                .map_err(|e| status::from_site(&c.metrics, &e))?;
            tracing::info!(
                created = opened.created,
                last_seq = opened.last_seq,
                "session opened"
            );
            Ok(Response::new(pb::OpenSessionResponse {
                format_version: FORMAT_VERSION,
                trajectory: opened.trajectory,
                last_acked_seq: opened.last_seq,
                created: opened.created,
                map_version,
            }))
        }
        .instrument(span)
        .await
    }

    async fn upload(&self, request: Request<pb::UploadBatch>) -> Result<Response<pb::Ack>, Status> {
        let r = request.get_ref();
        let span = tracing::error_span!(
            "upload", site = %r.site, robot = %r.robot_id, session = %r.session_uuid, seq = r.seq
        );
        async {
            let c = &self.context;
            c.metrics.add_bytes_in(r.encoded_len());
            let (grant, site) = c.site(&request, &r.site)?;
            check_robot(c, &grant.robot_id, &r.robot_id)?;
            let batch = UploadBatch::try_from(r).map_err(|e| {
                tracing::warn!("malformed batch refused: {e}");
                status::from_conversion(&c.metrics, &e)
            })?;
            let ack = site.upload(batch).await.map_err(|e| {
                tracing::warn!("upload refused: {e}");
                status::from_site(&c.metrics, &e)
            })?;
            Ok(Response::new(pb::Ack {
                format_version: FORMAT_VERSION,
                session_uuid: r.session_uuid.clone(),
                seq: ack.seq,
                map_version: ack.map_version,
                duplicate: ack.duplicate,
                session_end_pose: ack.session_end_pose.as_ref().map(proto::pose_to_pb),
            }))
        }
        .instrument(span)
        .await
    }

    async fn close_session(
        &self,
        request: Request<pb::CloseSessionRequest>,
    ) -> Result<Response<pb::CloseSessionResponse>, Status> {
        let r = request.get_ref();
        let span = tracing::error_span!(
            "close_session", site = %r.site, robot = %r.robot_id, session = %r.session_uuid
        );
        async {
            let c = &self.context;
            c.metrics.add_bytes_in(r.encoded_len());
            let (grant, site) = c.site(&request, &r.site)?;
            check_robot(c, &grant.robot_id, &r.robot_id)?;
            let map_version = site
                .close_session(&r.robot_id, &r.session_uuid)
                .await
                .map_err(|e| status::from_site(&c.metrics, &e))?;
            tracing::info!("session closed");
            Ok(Response::new(pb::CloseSessionResponse {
                format_version: FORMAT_VERSION,
                map_version,
            }))
        }
        .instrument(span)
        .await
    }
}

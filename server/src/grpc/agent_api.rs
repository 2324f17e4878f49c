//! `AgentService`: sessions and uploads from robots.

use prost::Message as _;
use proto::{FORMAT_VERSION, UploadBatch, pb};
use tonic::{Request, Response, Status};

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

#[tonic::async_trait]
impl pb::agent_service_server::AgentService for AgentApi {
    async fn open_session(
        &self,
        request: Request<pb::OpenSessionRequest>,
    ) -> Result<Response<pb::OpenSessionResponse>, Status> {
        let c = &self.context;
        let r = request.get_ref();
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
            site = %r.site, robot = %r.robot_id, session = %r.session_uuid,
            created = opened.created, last_seq = opened.last_seq, "session opened"
        );
        Ok(Response::new(pb::OpenSessionResponse {
            format_version: FORMAT_VERSION,
            trajectory: opened.trajectory,
            last_acked_seq: opened.last_seq,
            created: opened.created,
            map_version,
        }))
    }

    async fn upload(&self, request: Request<pb::UploadBatch>) -> Result<Response<pb::Ack>, Status> {
        let c = &self.context;
        let r = request.get_ref();
        c.metrics.add_bytes_in(r.encoded_len());
        let (grant, site) = c.site(&request, &r.site)?;
        check_robot(c, &grant.robot_id, &r.robot_id)?;
        let batch = UploadBatch::try_from(r).map_err(|e| {
            tracing::warn!(site = %r.site, robot = %r.robot_id, "malformed batch refused: {e}");
            status::from_conversion(&c.metrics, &e)
        })?;
        let ack = site.upload(batch).await.map_err(|e| {
            tracing::warn!(site = %r.site, robot = %r.robot_id, seq = r.seq, "upload refused: {e}");
            status::from_site(&c.metrics, &e)
        })?;
        Ok(Response::new(pb::Ack {
            format_version: FORMAT_VERSION,
            session_uuid: r.session_uuid.clone(),
            seq: ack.seq,
            map_version: ack.map_version,
            duplicate: ack.duplicate,
        }))
    }

    async fn close_session(
        &self,
        request: Request<pb::CloseSessionRequest>,
    ) -> Result<Response<pb::CloseSessionResponse>, Status> {
        let c = &self.context;
        let r = request.get_ref();
        c.metrics.add_bytes_in(r.encoded_len());
        let (grant, site) = c.site(&request, &r.site)?;
        check_robot(c, &grant.robot_id, &r.robot_id)?;
        let map_version = site
            .close_session(&r.robot_id, &r.session_uuid)
            .await
            .map_err(|e| status::from_site(&c.metrics, &e))?;
        tracing::info!(site = %r.site, robot = %r.robot_id, session = %r.session_uuid, "session closed");
        Ok(Response::new(pb::CloseSessionResponse {
            format_version: FORMAT_VERSION,
            map_version,
        }))
    }
}

//! [`MapUplink`] over zenoh: every call is one query to the site's queryable (`evermap/<site>/api`), the
//! server answering through the same handlers as gRPC; versions arrive as publications on
//! `evermap/<site>/version`. The token travels inside each request.

use std::time::Duration;

use prost::Message as _;
use proto::{FORMAT_VERSION, MapDelta, pb};
use zenoh::query::ConsolidationMode;

use super::grpc_uplink::from_status;
use super::{Acked, MapUplink, OpenedSession, UplinkError, VersionStream, ZenohLinkOptions};
use proto::{zenoh_api_key as api_key, zenoh_version_key as version_key};

/// Publications buffered between the zenoh subscriber and a slow watcher (older ones are dropped: a
/// watcher only needs the newest version).
const WATCH_BUFFER: usize = 16;

/// The zenoh uplink for one site. Cheap to clone (clones share the zenoh session).
#[derive(Clone)]
pub struct ZenohUplink {
    session: zenoh::Session,
    site: String,
    token: String,
    call_timeout: Duration,
}

/// A zenoh call failed: `what` names it, zenoh's error is kept as the source.
fn unavailable(what: &str, e: zenoh::Error) -> UplinkError {
    UplinkError::Unavailable {
        what: format!("zenoh {what}"),
        source: Some(e),
    }
}

impl ZenohUplink {
    /// Opens a zenoh session with `options` and uses it for `site` with `token`; each call waits at most
    /// `call_timeout` for its answer.
    pub async fn connect(
        options: &ZenohLinkOptions,
        site: &str,
        token: &str,
        call_timeout: Duration,
    ) -> Result<Self, UplinkError> {
        let config = options
            .to_zenoh_config()
            .map_err(|e| UplinkError::Settings {
                what: format!("zenoh: {e}"),
                source: Some(Box::new(e)),
            })?;
        let session = zenoh::open(config)
            .await
            .map_err(|e| unavailable("session", e))?;
        Ok(Self::with_session(session, site, token, call_timeout))
    }

    /// Uses an open zenoh session (several sites' uplinks can share one).
    pub fn with_session(
        session: zenoh::Session,
        site: &str,
        token: &str,
        call_timeout: Duration,
    ) -> Self {
        Self {
            session,
            site: site.to_owned(),
            token: token.to_owned(),
            call_timeout,
        }
    }

    /// Sends one request and collects the replies (several for a delta), turning a refusal into the same
    /// [`UplinkError`] the gRPC uplink gives.
    async fn call(
        &self,
        request: pb::zenoh_request::Request,
    ) -> Result<Vec<pb::zenoh_reply::Reply>, UplinkError> {
        let payload = pb::ZenohRequest {
            format_version: FORMAT_VERSION,
            token: self.token.clone(),
            request: Some(request),
        }
        .encode_to_vec();
        let replies = self
            .session
            .get(api_key(&self.site))
            .payload(payload)
            .consolidation(ConsolidationMode::None)
            .timeout(self.call_timeout)
            .await
            .map_err(|e| unavailable("query", e))?;
        let mut answers = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            let sample = reply.result().map_err(|e| {
                UplinkError::unavailable(format!("zenoh reply: {:?}", e.payload().to_bytes()))
            })?;
            let decoded = pb::ZenohReply::decode(&*sample.payload().to_bytes()).map_err(|e| {
                UplinkError::Malformed(proto::ConversionError::Decode {
                    message: "ZenohReply",
                    source: proto::ErrorSource::new(e),
                })
            })?;
            proto::check_format_version("ZenohReply", decoded.format_version)?;
            match decoded.reply {
                Some(pb::zenoh_reply::Reply::Error(status)) => {
                    return Err(from_zenoh_status(&status));
                }
                Some(reply) => answers.push(reply),
                None => {
                    return Err(UplinkError::Malformed(
                        proto::ConversionError::MissingField {
                            message: "ZenohReply",
                            field: "reply",
                        },
                    ));
                }
            }
        }
        if answers.is_empty() {
            return Err(UplinkError::unavailable(format!(
                "no answer from {} within {:?} (is the server's zenoh front end reachable?)",
                api_key(&self.site),
                self.call_timeout
            )));
        }
        Ok(answers)
    }

    async fn call_one(
        &self,
        request: pb::zenoh_request::Request,
    ) -> Result<pb::zenoh_reply::Reply, UplinkError> {
        let mut answers = self.call(request).await?;
        if answers.len() != 1 {
            return Err(UplinkError::unavailable(format!(
                "{} answers to one request: is more than one server serving site {:?}?",
                answers.len(),
                self.site
            )));
        }
        Ok(answers.remove(0))
    }
}

/// The refusal as the gRPC uplink would report it.
fn from_zenoh_status(status: &pb::ZenohStatus) -> UplinkError {
    let mut grpc = tonic::Status::new(tonic::Code::from(status.code), status.message.clone());
    if status.expected_seq > 0
        && let Ok(value) = status.expected_seq.to_string().parse()
    {
        grpc.metadata_mut()
            .insert(super::grpc_uplink::EXPECTED_SEQ_METADATA, value);
    }
    from_status(&grpc)
}

fn unexpected(what: &'static str, reply: &pb::zenoh_reply::Reply) -> UplinkError {
    UplinkError::Malformed(proto::ConversionError::WrongKind {
        message: "ZenohReply",
        field: "reply",
        expected: what,
        got: reply_name(reply),
    })
}

fn reply_name(reply: &pb::zenoh_reply::Reply) -> &'static str {
    match reply {
        pb::zenoh_reply::Reply::Opened(_) => "OpenSessionResponse",
        pb::zenoh_reply::Reply::Ack(_) => "Ack",
        pb::zenoh_reply::Reply::Closed(_) => "CloseSessionResponse",
        pb::zenoh_reply::Reply::Version(_) => "MapVersion",
        pb::zenoh_reply::Reply::Delta(_) => "MapDelta",
        pb::zenoh_reply::Reply::Error(_) => "ZenohStatus",
    }
}

impl MapUplink for ZenohUplink {
    async fn open_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<OpenedSession, UplinkError> {
        let request = pb::zenoh_request::Request::OpenSession(pb::OpenSessionRequest {
            format_version: FORMAT_VERSION,
            site: self.site.clone(),
            robot_id: robot_id.to_owned(),
            session_uuid: session_uuid.to_owned(),
        });
        match self.call_one(request).await? {
            pb::zenoh_reply::Reply::Opened(r) => Ok(OpenedSession {
                trajectory: r.trajectory,
                last_acked_seq: r.last_acked_seq,
                created: r.created,
                map_version: r.map_version,
            }),
            other => Err(unexpected("OpenSessionResponse", &other)),
        }
    }

    async fn upload(&mut self, batch: &pb::UploadBatch) -> Result<Acked, UplinkError> {
        let request = pb::zenoh_request::Request::Upload(batch.clone());
        match self.call_one(request).await? {
            pb::zenoh_reply::Reply::Ack(ack) => Acked::from_wire(&ack),
            other => Err(unexpected("Ack", &other)),
        }
    }

    async fn close_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<u64, UplinkError> {
        let request = pb::zenoh_request::Request::CloseSession(pb::CloseSessionRequest {
            format_version: FORMAT_VERSION,
            site: self.site.clone(),
            robot_id: robot_id.to_owned(),
            session_uuid: session_uuid.to_owned(),
        });
        match self.call_one(request).await? {
            pb::zenoh_reply::Reply::Closed(r) => Ok(r.map_version),
            other => Err(unexpected("CloseSessionResponse", &other)),
        }
    }

    async fn map_version(&mut self) -> Result<u64, UplinkError> {
        let request = pb::zenoh_request::Request::GetVersion(pb::GetVersionRequest {
            site: self.site.clone(),
        });
        match self.call_one(request).await? {
            pb::zenoh_reply::Reply::Version(v) => Ok(v.version),
            other => Err(unexpected("MapVersion", &other)),
        }
    }

    async fn delta_since(&mut self, since: u64) -> Result<MapDelta, UplinkError> {
        let request = pb::zenoh_request::Request::GetDelta(pb::GetDeltaRequest {
            site: self.site.clone(),
            since_version: since,
        });
        let mut chunks = Vec::new();
        for reply in self.call(request).await? {
            match reply {
                pb::zenoh_reply::Reply::Delta(chunk) => chunks.push(chunk),
                other => return Err(unexpected("MapDelta", &other)),
            }
        }
        if !chunks.last().is_some_and(|c| c.last) {
            return Err(UplinkError::unavailable(format!(
                "delta since {since} arrived incomplete ({} chunks, no last one)",
                chunks.len()
            )));
        }
        Ok(MapDelta::from_pb_chunks(&chunks)?)
    }

    async fn watch_versions(&mut self) -> Result<VersionStream, UplinkError> {
        // Subscribe first, then read the current version: a version made in between is seen twice at
        // worst, never missed.
        let subscriber = self
            .session
            .declare_subscriber(version_key(&self.site))
            .await
            .map_err(|e| unavailable("subscriber", e))?;
        let current = self.map_version().await?;
        let (sender, receiver) = tokio::sync::mpsc::channel(WATCH_BUFFER);
        let _ = sender.try_send(Ok(current));
        tokio::spawn(async move {
            loop {
                tokio::select! {
                    () = sender.closed() => break,
                    sample = subscriber.recv_async() => {
                        let Ok(sample) = sample else { break };
                        let version = pb::MapVersion::decode(&*sample.payload().to_bytes())
                            .map(|v| v.version)
                            .map_err(|e| {
                                UplinkError::Malformed(proto::ConversionError::Decode {
                                    message: "MapVersion",
                                    source: proto::ErrorSource::new(e),
                                })
                            });
                        // A full buffer means the watcher is behind: it will read a newer version anyway.
                        let _ = sender.try_send(version);
                    }
                }
            }
        });
        Ok(Box::pin(tokio_stream::wrappers::ReceiverStream::new(
            receiver,
        )))
    }
}

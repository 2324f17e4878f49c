//! The zenoh front end: the same agent uplink and map reads as gRPC, for robots that reach the server
//! through zenoh routers. Per site it serves the queryable `evermap/<site>/api` (each query one
//! `ZenohRequest`, answered by one `ZenohReply`, a delta by one reply per chunk) and publishes every new
//! version on `evermap/<site>/version`. Requests go through the gRPC handlers themselves ([`AgentApi`],
//! [`MapApi`]), token included, so both transports end in the same site task with the same checks,
//! errors and metrics. Before serving its sites it looks for another owner of each
//! ([`ensure_no_other_owner`]): an instance refuses to start while another one behind the same routers
//! serves one of its sites.

mod site_ownership;

pub use site_ownership::{OWNER_WAIT, ensure_no_other_owner};

use std::sync::Arc;

use prost::Message as _;
use proto::pb::agent_service_server::AgentService as _;
use proto::pb::map_service_server::MapService as _;
use proto::pb::zenoh_reply::Reply;
use proto::pb::zenoh_request::Request;
use proto::{FORMAT_VERSION, pb};
use proto::{ZenohLinkOptions, zenoh_api_key, zenoh_version_key};
use tokio::sync::Semaphore;
use tokio::task::JoinHandle;
use tokio_stream::StreamExt as _;
use tonic::metadata::MetadataValue;
use tracing::Instrument as _;

use crate::grpc::status::EXPECTED_SEQ_METADATA;
use crate::grpc::{AgentApi, ApiContext, MapApi, version_to_pb};
use crate::site::site_span;

/// Why the zenoh front end could not start.
#[derive(Debug, thiserror::Error)]
pub enum ZenohFrontError {
    /// The options are invalid.
    #[error(transparent)]
    Options(#[from] proto::ZenohLinkOptionsError),
    /// zenoh refused (bad endpoint, port taken, ...).
    #[error("zenoh: {0}")]
    Zenoh(#[source] zenoh::Error),
    /// Another server instance behind the same routers serves the site.
    #[error(
        "site {site:?} is already served by another server instance behind the zenoh routers (it answers \
         on evermap/{site}/api): a site has one owner at a time; take it off the \
         other instance's [[sites]] (and restart that one) or off this one's"
    )]
    SiteServedElsewhere {
        /// The site.
        site: String,
    },
}

/// A running zenoh front end; stop it with [`ZenohFront::shutdown`].
pub struct ZenohFront {
    session: zenoh::Session,
    tasks: Vec<JoinHandle<()>>,
}

impl ZenohFront {
    /// Opens a zenoh session with `options` and serves every site of `context`, answering at most
    /// `max_in_flight` queries of one site at a time (more wait in zenoh's bounded queryable queue).
    pub async fn start(
        options: &ZenohLinkOptions,
        context: ApiContext,
        max_in_flight: usize,
    ) -> Result<Self, ZenohFrontError> {
        ensure_no_other_owner(options, context.sites.keys(), OWNER_WAIT).await?;
        let session = zenoh::open(options.to_zenoh_config()?)
            .await
            .map_err(ZenohFrontError::Zenoh)?;
        let agent = AgentApi::new(context.clone());
        let map = MapApi::new(context.clone());
        let mut tasks = Vec::new();
        for (id, handle) in context.sites.iter() {
            let queryable = session
                .declare_queryable(zenoh_api_key(id))
                .await
                .map_err(ZenohFrontError::Zenoh)?;
            let (agent, map) = (agent.clone(), map.clone());
            let in_flight = Arc::new(Semaphore::new(max_in_flight.max(1)));
            tasks.push(tokio::spawn(
                async move {
                    while let Ok(query) = queryable.recv_async().await {
                        // One task per query: a slow upload must not hold up a version read. The site task
                        // still applies one site's changes in order.
                        let Ok(permit) = Arc::clone(&in_flight).acquire_owned().await else {
                            break;
                        };
                        let (agent, map) = (agent.clone(), map.clone());
                        tokio::spawn(
                            async move {
                                let _permit = permit;
                                let payload = query.payload().map(|p| p.to_bytes().into_owned());
                                for reply in answer(&agent, &map, payload.as_deref()).await {
                                    let bytes = reply.encode_to_vec();
                                    if let Err(e) =
                                        query.reply(query.key_expr().clone(), bytes).await
                                    {
                                        tracing::warn!("zenoh reply to {}: {e}", query.key_expr());
                                        break;
                                    }
                                }
                            }
                            .in_current_span(),
                        );
                    }
                }
                .instrument(site_span(id)),
            ));
            let publisher = session
                .declare_publisher(zenoh_version_key(id))
                .await
                .map_err(ZenohFrontError::Zenoh)?;
            let mut versions = handle.subscribe();
            let site = id.clone();
            tasks.push(tokio::spawn(
                async move {
                    loop {
                        let info = *versions.borrow_and_update();
                        let bytes = version_to_pb(&site, &info).encode_to_vec();
                        if let Err(e) = publisher.put(bytes).await {
                            tracing::warn!("zenoh version publication: {e}");
                        }
                        if versions.changed().await.is_err() {
                            break;
                        }
                    }
                }
                .instrument(site_span(id)),
            ));
        }
        tracing::info!(
            sites = context.sites.len(),
            zid = %session.zid(),
            "zenoh front end serving"
        );
        Ok(Self { session, tasks })
    }

    /// Stops serving and closes the zenoh session.
    pub async fn shutdown(self) {
        for task in &self.tasks {
            task.abort();
        }
        for task in self.tasks {
            let _ = task.await;
        }
        if let Err(e) = self.session.close().await {
            tracing::warn!("closing the zenoh session: {e}");
        }
    }
}

fn refusal(status: &tonic::Status) -> pb::ZenohReply {
    let expected_seq = status
        .metadata()
        .get(EXPECTED_SEQ_METADATA)
        .and_then(|v| v.to_str().ok()?.parse().ok())
        .unwrap_or(0);
    pb::ZenohReply {
        format_version: FORMAT_VERSION,
        reply: Some(pb::zenoh_reply::Reply::Error(pb::ZenohStatus {
            code: status.code() as i32,
            message: status.message().to_owned(),
            expected_seq,
        })),
    }
}

fn reply(reply: Reply) -> pb::ZenohReply {
    pb::ZenohReply {
        format_version: FORMAT_VERSION,
        reply: Some(reply),
    }
}

/// Decodes one query, runs it through the gRPC handler with the request's token, and gives the replies
/// (public for the fuzz harness, which feeds it hostile payloads without a zenoh session).
pub async fn answer(agent: &AgentApi, map: &MapApi, payload: Option<&[u8]>) -> Vec<pb::ZenohReply> {
    let request = match payload.map(pb::ZenohRequest::decode) {
        None => {
            return vec![refusal(&tonic::Status::invalid_argument(
                "the query carries no ZenohRequest payload",
            ))];
        }
        Some(Err(e)) => {
            return vec![refusal(&tonic::Status::invalid_argument(format!(
                "the payload is not a ZenohRequest: {e}"
            )))];
        }
        Some(Ok(request)) => request,
    };
    if let Err(e) = proto::check_format_version("ZenohRequest", request.format_version) {
        return vec![refusal(&tonic::Status::invalid_argument(e.to_string()))];
    }
    let Ok(bearer) = MetadataValue::try_from(format!("Bearer {}", request.token)) else {
        return vec![refusal(&tonic::Status::unauthenticated(
            "the token must be printable ASCII",
        ))];
    };
    let with_token = TokenStamp(bearer);
    let result = match request.request {
        None => Err(tonic::Status::invalid_argument(
            "ZenohRequest.request is missing",
        )),
        Some(Request::OpenSession(r)) => agent
            .open_session(with_token.on(r))
            .await
            .map(|r| vec![reply(Reply::Opened(r.into_inner()))]),
        Some(Request::Upload(r)) => agent
            .upload(with_token.on(r))
            .await
            .map(|r| vec![reply(Reply::Ack(r.into_inner()))]),
        Some(Request::CloseSession(r)) => agent
            .close_session(with_token.on(r))
            .await
            .map(|r| vec![reply(Reply::Closed(r.into_inner()))]),
        Some(Request::GetVersion(r)) => map
            .get_version(with_token.on(r))
            .await
            .map(|r| vec![reply(Reply::Version(r.into_inner()))]),
        Some(Request::GetDelta(r)) => match map.get_delta(with_token.on(r)).await {
            Err(status) => Err(status),
            Ok(stream) => {
                let mut chunks = Vec::new();
                let mut stream = stream.into_inner();
                let mut failed = None;
                while let Some(chunk) = stream.next().await {
                    match chunk {
                        Ok(chunk) => chunks.push(reply(Reply::Delta(chunk))),
                        Err(status) => {
                            failed = Some(status);
                            break;
                        }
                    }
                }
                failed.map_or(Ok(chunks), Err)
            }
        },
    };
    result.unwrap_or_else(|status| vec![refusal(&status)])
}

/// Puts the query's token where the gRPC handlers look for it.
struct TokenStamp(MetadataValue<tonic::metadata::Ascii>);

impl TokenStamp {
    fn on<T>(&self, message: T) -> tonic::Request<T> {
        let mut request = tonic::Request::new(message);
        request
            .metadata_mut()
            .insert("authorization", self.0.clone());
        request
    }
}

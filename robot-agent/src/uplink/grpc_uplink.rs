//! [`MapUplink`] over gRPC (tonic), with the robot's bearer token on every call.

use std::time::Duration;

use proto::{FORMAT_VERSION, MapDelta, pb};
use tokio_stream::StreamExt as _;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::transport::{Channel, Endpoint};

use super::{Acked, MapUplink, OpenedSession, UplinkError, VersionStream};

/// Metadata key carrying the next sequence number on a sequence-gap refusal (see the server).
pub(super) const EXPECTED_SEQ_METADATA: &str = "evermap-expected-seq";

/// Adds `authorization: Bearer <token>` to every request.
#[derive(Clone)]
pub struct BearerToken(MetadataValue<Ascii>);

impl Interceptor for BearerToken {
    fn call(
        &mut self,
        mut request: tonic::Request<()>,
    ) -> Result<tonic::Request<()>, tonic::Status> {
        request
            .metadata_mut()
            .insert("authorization", self.0.clone());
        Ok(request)
    }
}

type Authed = tonic::service::interceptor::InterceptedService<Channel, BearerToken>;

/// The gRPC uplink. Connects lazily and reconnects by itself; each unary call is bounded by
/// `call_timeout`. Cheap to clone (clones share the connection).
#[derive(Clone)]
pub struct GrpcUplink {
    site: String,
    agent: pb::agent_service_client::AgentServiceClient<Authed>,
    map: pb::map_service_client::MapServiceClient<Authed>,
    call_timeout: Duration,
}

pub(super) fn from_status(status: &tonic::Status) -> UplinkError {
    use tonic::Code;
    match status.code() {
        Code::Unavailable
        | Code::DeadlineExceeded
        | Code::Cancelled
        | Code::Unknown
        | Code::Aborted => UplinkError::unavailable_because(status.message(), status.clone()),
        Code::FailedPrecondition => status
            .metadata()
            .get(EXPECTED_SEQ_METADATA)
            .and_then(|v| v.to_str().ok()?.parse().ok())
            .map_or_else(
                || UplinkError::Rejected {
                    code: status.code(),
                    message: status.message().to_owned(),
                },
                |expected| UplinkError::SequenceGap { expected },
            ),
        code => UplinkError::Rejected {
            code,
            message: status.message().to_owned(),
        },
    }
}

/// How the agent checks a TLS server: the CA that signed its certificate and, when the URL's host is not
/// the name in the certificate, that name.
#[derive(Clone, Debug)]
pub struct ClientTls {
    /// The certificate authority (PEM).
    pub ca_pem: Vec<u8>,
    /// The server name to verify instead of the URL's host.
    pub domain: Option<String>,
}

impl GrpcUplink {
    /// An uplink to `url` (e.g. `http://127.0.0.1:50051`) for `site` with `token`. Does not connect yet.
    /// `max_message_bytes` bounds messages both ways (must match the server's).
    pub fn new(
        url: &str,
        site: &str,
        token: &str,
        max_message_bytes: usize,
        call_timeout: Duration,
    ) -> Result<Self, UplinkError> {
        Self::with_tls(url, site, token, max_message_bytes, call_timeout, None)
    }

    /// [`Self::new`] over TLS when `tls` is given (use an `https://` URL).
    pub fn with_tls(
        url: &str,
        site: &str,
        token: &str,
        max_message_bytes: usize,
        call_timeout: Duration,
        tls: Option<&ClientTls>,
    ) -> Result<Self, UplinkError> {
        let mut endpoint = Endpoint::from_shared(url.to_owned())
            .map_err(|e| UplinkError::Settings {
                what: format!("bad server url {url:?}: {e}"),
                source: Some(Box::new(e)),
            })?
            .connect_timeout(call_timeout)
            .tcp_nodelay(true);
        if let Some(tls) = tls {
            let mut config = tonic::transport::ClientTlsConfig::new()
                .ca_certificate(tonic::transport::Certificate::from_pem(&tls.ca_pem));
            if let Some(domain) = &tls.domain {
                config = config.domain_name(domain.clone());
            }
            endpoint = endpoint
                .tls_config(config)
                .map_err(|e| UplinkError::Settings {
                    what: format!("TLS: {e}"),
                    source: Some(Box::new(e)),
                })?;
        }
        let channel = endpoint.connect_lazy();
        let token: MetadataValue<Ascii> =
            format!("Bearer {token}")
                .parse()
                .map_err(|e| UplinkError::Settings {
                    what: "the token must be printable ASCII".into(),
                    source: Some(Box::new(e)),
                })?;
        let auth = BearerToken(token);
        Ok(Self {
            site: site.to_owned(),
            agent: pb::agent_service_client::AgentServiceClient::with_interceptor(
                channel.clone(),
                auth.clone(),
            )
            .max_decoding_message_size(max_message_bytes)
            .max_encoding_message_size(max_message_bytes),
            map: pb::map_service_client::MapServiceClient::with_interceptor(channel, auth)
                .max_decoding_message_size(max_message_bytes)
                .max_encoding_message_size(max_message_bytes),
            call_timeout,
        })
    }

    async fn bounded<T>(
        &self,
        call: impl Future<Output = Result<tonic::Response<T>, tonic::Status>>,
    ) -> Result<T, UplinkError> {
        match tokio::time::timeout(self.call_timeout, call).await {
            Ok(Ok(response)) => Ok(response.into_inner()),
            Ok(Err(status)) => Err(from_status(&status)),
            Err(_) => Err(UplinkError::unavailable(format!(
                "no answer within {:?}",
                self.call_timeout
            ))),
        }
    }

    /// The site's rendered map (PNG, pgm, yaml).
    pub async fn map_image(&mut self, resolution: f64) -> Result<pb::MapImage, UplinkError> {
        let mut client = self.map.clone();
        let request = pb::GetMapImageRequest {
            site: self.site.clone(),
            resolution,
        };
        self.bounded(client.get_map_image(request)).await
    }
}

impl MapUplink for GrpcUplink {
    async fn open_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<OpenedSession, UplinkError> {
        let mut client = self.agent.clone();
        let request = pb::OpenSessionRequest {
            format_version: FORMAT_VERSION,
            site: self.site.clone(),
            robot_id: robot_id.to_owned(),
            session_uuid: session_uuid.to_owned(),
        };
        let r = self.bounded(client.open_session(request)).await?;
        Ok(OpenedSession {
            trajectory: r.trajectory,
            last_acked_seq: r.last_acked_seq,
            created: r.created,
            map_version: r.map_version,
        })
    }

    async fn upload(&mut self, batch: &pb::UploadBatch) -> Result<Acked, UplinkError> {
        let mut client = self.agent.clone();
        let ack = self.bounded(client.upload(batch.clone())).await?;
        Acked::from_wire(&ack)
    }

    async fn close_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<u64, UplinkError> {
        let mut client = self.agent.clone();
        let request = pb::CloseSessionRequest {
            format_version: FORMAT_VERSION,
            site: self.site.clone(),
            robot_id: robot_id.to_owned(),
            session_uuid: session_uuid.to_owned(),
        };
        Ok(self
            .bounded(client.close_session(request))
            .await?
            .map_version)
    }

    async fn map_version(&mut self) -> Result<u64, UplinkError> {
        let mut client = self.map.clone();
        let request = pb::GetVersionRequest {
            site: self.site.clone(),
        };
        Ok(self.bounded(client.get_version(request)).await?.version)
    }

    async fn delta_since(&mut self, since: u64) -> Result<MapDelta, UplinkError> {
        let mut client = self.map.clone();
        let request = pb::GetDeltaRequest {
            site: self.site.clone(),
            since_version: since,
        };
        let timeout = self.call_timeout;
        let collect = async {
            let mut stream = client
                .get_delta(request)
                .await
                .map_err(|s| from_status(&s))?
                .into_inner();
            let mut chunks = Vec::new();
            while let Some(chunk) = stream.next().await {
                let chunk = chunk.map_err(|s| from_status(&s))?;
                let last = chunk.last;
                chunks.push(chunk);
                if last {
                    break;
                }
            }
            Ok::<_, UplinkError>(chunks)
        };
        let chunks = tokio::time::timeout(timeout, collect).await.map_err(|_| {
            UplinkError::unavailable(format!("delta not received within {timeout:?}"))
        })??;
        Ok(MapDelta::from_pb_chunks(&chunks)?)
    }

    async fn watch_versions(&mut self) -> Result<VersionStream, UplinkError> {
        let mut client = self.map.clone();
        let request = pb::WatchRequest {
            site: self.site.clone(),
        };
        let stream = self.bounded(client.watch(request)).await?;
        Ok(Box::pin(stream.map(|item| {
            item.map(|v| v.version).map_err(|s| from_status(&s))
        })))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // Reference: issue 35 item 6 — settings that cannot work are the agent's own error, kept as the
    // source, and retrying them is not offered.
    #[tokio::test]
    async fn unusable_settings_are_refused_for_good_with_their_cause() {
        let second = Duration::from_secs(1);
        for (url, token, said) in [
            ("not a url\n", "t0k3n", "bad server url"),
            ("http://127.0.0.1:1", "t0k3n\u{7}é", "printable ASCII"),
        ] {
            let Err(error) = GrpcUplink::new(url, "site", token, 1 << 20, second) else {
                panic!("{url:?} {token:?} accepted");
            };
            assert!(
                matches!(error, UplinkError::Settings { .. }) && !error.is_transient(),
                "{error:?}"
            );
            assert!(error.to_string().contains(said), "{error}");
            assert!(std::error::Error::source(&error).is_some(), "{error:?}");
        }
    }

    // Reference: issue 35 item 6 — a server that cannot answer now is a retryable error that keeps the
    // gRPC status (and what caused it) as its source, not only the status's message.
    #[test]
    fn an_unavailable_server_keeps_its_status_as_the_source() {
        let error = from_status(&tonic::Status::unavailable("connection refused"));
        assert!(error.is_transient(), "{error:?}");
        assert_eq!(error.to_string(), "server unavailable: connection refused");
        let source = std::error::Error::source(&error).expect("the status is kept");
        let status = source
            .downcast_ref::<tonic::Status>()
            .expect("the source is the gRPC status");
        assert_eq!(status.code(), tonic::Code::Unavailable);
    }
}

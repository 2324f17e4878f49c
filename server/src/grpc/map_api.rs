//! `MapService`: reading site maps.

use std::pin::Pin;

use prost::Message as _;
use proto::{FORMAT_VERSION, pb};
use tokio_stream::{Stream, StreamExt as _};
use tonic::{Request, Response, Status};

use super::{ApiContext, status};
use crate::map_image_bytes::encode_map;
use crate::site::{VersionInfo, copy_counts};

/// The `MapService` implementation.
#[derive(Clone)]
pub struct MapApi {
    context: ApiContext,
}

impl MapApi {
    /// Serves the context's sites.
    pub fn new(context: ApiContext) -> Self {
        Self { context }
    }
}

/// The wire form of a published version.
pub fn version_to_pb(site: &str, info: &VersionInfo) -> pb::MapVersion {
    let c = &info.counts;
    pb::MapVersion {
        format_version: FORMAT_VERSION,
        site: site.to_owned(),
        version: info.version,
        counts: Some(copy_counts!(c => pb::MapCounts {})),
    }
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl pb::map_service_server::MapService for MapApi {
    async fn list_sites(
        &self,
        request: Request<pb::ListSitesRequest>,
    ) -> Result<Response<pb::ListSitesResponse>, Status> {
        let c = &self.context;
        let grant = c
            .auth
            .grant_from(request.metadata(), super::peer_ip(&request), super::now())
            .map_err(|s| status::counted(&c.metrics, s))?;
        let sites = c
            .sites
            .get(&grant.site)
            .map(|s| version_to_pb(s.site(), &s.current()))
            .into_iter()
            .collect();
        Ok(Response::new(pb::ListSitesResponse { sites }))
    }

    async fn get_version(
        &self,
        request: Request<pb::GetVersionRequest>,
    ) -> Result<Response<pb::MapVersion>, Status> {
        let (_, site) = self.context.site(&request, &request.get_ref().site)?;
        Ok(Response::new(version_to_pb(site.site(), &site.current())))
    }

    type GetDeltaStream = BoxStream<pb::MapDelta>;

    async fn get_delta(
        &self,
        request: Request<pb::GetDeltaRequest>,
    ) -> Result<Response<Self::GetDeltaStream>, Status> {
        let c = &self.context;
        let (_, site) = c.site(&request, &request.get_ref().site)?;
        let delta = site
            .delta_since(request.get_ref().since_version)
            .await
            .map_err(|e| status::from_site(&c.metrics, &e))?;
        let chunk_bytes = c.delta_chunk_bytes;
        // Compressing grids is CPU work: keep it off the async workers.
        let chunks = tokio::task::spawn_blocking(move || delta.to_pb_chunks(chunk_bytes))
            .await
            .map_err(|e| status::internal("compressing the delta", e))?;
        c.metrics
            .add_bytes_out(chunks.iter().map(prost::Message::encoded_len).sum());
        Ok(Response::new(Box::pin(tokio_stream::iter(
            chunks.into_iter().map(Ok),
        ))))
    }

    async fn get_submap(
        &self,
        request: Request<pb::GetSubmapRequest>,
    ) -> Result<Response<pb::Submap>, Status> {
        let c = &self.context;
        let r = request.get_ref();
        let (_, site) = c.site(&request, &r.site)?;
        let id = r.id.ok_or_else(|| {
            status::counted(
                &c.metrics,
                Status::invalid_argument("GetSubmapRequest.id is missing"),
            )
        })?;
        let submap = site
            .submap(id.into(), r.revision)
            .await
            .map_err(|e| status::from_site(&c.metrics, &e))?;
        let wire = pb::Submap::from(&submap);
        c.metrics.add_bytes_out(wire.encoded_len());
        Ok(Response::new(wire))
    }

    async fn get_map_image(
        &self,
        request: Request<pb::GetMapImageRequest>,
    ) -> Result<Response<pb::MapImage>, Status> {
        let c = &self.context;
        let r = request.get_ref();
        let (_, site) = c.site(&request, &r.site)?;
        if !(r.resolution.is_finite() && r.resolution >= 0.0) {
            return Err(status::counted(
                &c.metrics,
                Status::invalid_argument("resolution must be a finite number ≥ 0"),
            ));
        }
        let rendered = site
            .render(r.resolution)
            .await
            .map_err(|e| status::from_site(&c.metrics, &e))?;
        let grid = rendered.grid.ok_or_else(|| {
            Status::not_found(format!("site {:?} has no finished submap yet", r.site))
        })?;
        let encoded = tokio::task::spawn_blocking(move || (encode_map(&grid), grid))
            .await
            .map_err(|e| status::internal("encoding the map", e))?;
        let (Some(image), grid) = encoded else {
            return Err(Status::internal("the map could not be encoded"));
        };
        let limits = grid.limits();
        let reply = pb::MapImage {
            format_version: FORMAT_VERSION,
            site: r.site.clone(),
            version: rendered.version,
            resolution: limits.resolution,
            origin_x: limits.origin.x,
            origin_y: limits.origin.y,
            width: image.width,
            height: image.height,
            png: image.png,
            pgm: image.pgm,
            yaml: image.yaml,
        };
        c.metrics.add_bytes_out(reply.encoded_len());
        Ok(Response::new(reply))
    }

    type WatchStream = BoxStream<pb::MapVersion>;

    async fn watch(
        &self,
        request: Request<pb::WatchRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        let (_, site) = self.context.site(&request, &request.get_ref().site)?;
        let name = site.site().to_owned();
        // The current version first, then each newly published one; ends when the site stops.
        let stream = tokio_stream::wrappers::WatchStream::new(site.subscribe())
            .map(move |info| Ok(version_to_pb(&name, &info)));
        Ok(Response::new(Box::pin(stream)))
    }
}

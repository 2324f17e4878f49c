//! The console's routes (listed in the `console` module docs and the README): the page, `/health`,
//! `/metrics`, the JSON API under `/api/` and the event stream. Handlers only read: they ask the site
//! tasks and render images on the blocking pool.

use std::convert::Infallible;
use std::sync::Arc;

use axum::Router;
use axum::body::Body;
use axum::extract::{Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, Uri, header};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use mapping::geometry::{Rigid2, Rigid2Ext as _};
use serde_json::{Value, json};
use tokio_stream::StreamExt as _;
use tokio_stream::wrappers::BroadcastStream;

use super::console_auth::{Authenticated, query_param};
use super::console_state::ConsoleState;
use super::map_images::{ImagePlacement, render_change_image};
use super::{ChangeImage, ConsoleError, MapImage};
use crate::site::{HistoryEntry, MapCounts, SessionView, SiteHandle};

/// The page: one HTML file with its CSS and JS inline.
const PAGE: &str = include_str!("page.html");

type Shared = Arc<ConsoleState>;

/// The console's routes over `state`.
pub fn router(state: Shared) -> Router {
    let guarded = Router::new()
        .route("/", get(page))
        .route("/metrics", get(metrics))
        .route("/api/sites", get(sites))
        .route("/api/sites/{site}", get(site))
        .route("/api/sites/{site}/versions", get(versions))
        .route("/api/sites/{site}/sessions", get(sessions))
        .route("/api/sites/{site}/robots", get(robots))
        .route("/api/sites/{site}/map", get(map_info))
        .route("/api/sites/{site}/map.png", get(map_png))
        .route("/api/sites/{site}/change", get(change_info))
        .route("/api/sites/{site}/change.png", get(change_png))
        .route("/api/events", get(events))
        .route_layer(middleware::from_fn_with_state(
            Arc::clone(&state),
            authorize,
        ));
    Router::new()
        .route("/health", get(health))
        .merge(guarded)
        .fallback(not_found)
        .with_state(state)
}

/// Lets requests with the operator token through; sets the cookie when it came as `?token=`.
async fn authorize(State(state): State<Shared>, request: Request, next: Next) -> Response {
    match state.auth.check(request.headers(), request.uri().query()) {
        Ok(how) => {
            let mut response = next.run(request).await;
            if how == Authenticated::Query
                && let Some(cookie) = state
                    .auth
                    .cookie()
                    .and_then(|c| HeaderValue::from_str(&c).ok())
            {
                response.headers_mut().append(header::SET_COOKIE, cookie);
            }
            response
        }
        Err(e) => ConsoleError::from(e).into_response(),
    }
}

async fn not_found(uri: Uri) -> Response {
    (
        StatusCode::NOT_FOUND,
        [(header::CONTENT_TYPE, "application/json")],
        json!({ "error": format!("no route {}", uri.path()) }).to_string(),
    )
        .into_response()
}

fn json_response(value: &Value) -> Response {
    (
        [
            (header::CONTENT_TYPE, "application/json"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        value.to_string(),
    )
        .into_response()
}

/// The entity tag of an image: what it shows (kind, versions) and at which cell size, so a restart with
/// another `map_resolution_m` does not pass for the same image.
fn image_etag(kind: &str, from: u64, to: u64, resolution: f64) -> String {
    let micrometres = (resolution * 1e6).round() as u64;
    format!("\"{kind}-{from}-{to}-{micrometres}um\"")
}

/// Whether the request's `If-None-Match` names `etag` (or `*`).
fn not_modified(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(|tag| tag.trim().trim_start_matches("W/"))
        .any(|tag| tag == etag || tag == "*")
}

/// How a PNG is answered: with its entity tag; one asked by version never changes and may be cached, one
/// asked as "now" (no version) must be revalidated (`If-None-Match`: 304 while the map is the same).
struct PngAnswer {
    etag: String,
    versioned: bool,
    map_version: u64,
}

impl PngAnswer {
    fn headers(&self, response: &mut Response) {
        let cache = if self.versioned {
            // A version's image never changes.
            "private, max-age=3600, immutable"
        } else {
            "private, no-cache"
        };
        let headers = response.headers_mut();
        headers.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
        if let Ok(v) = HeaderValue::from_str(&self.etag) {
            headers.insert(header::ETAG, v);
        }
        if let Ok(v) = HeaderValue::from_str(&self.map_version.to_string()) {
            headers.insert("x-evermap-map-version", v);
        }
    }

    /// 304 Not Modified when the request already holds this image.
    fn not_modified(&self, request: &HeaderMap) -> Option<Response> {
        not_modified(request, &self.etag).then(|| {
            let mut response = StatusCode::NOT_MODIFIED.into_response();
            self.headers(&mut response);
            response
        })
    }

    fn png(&self, png: Vec<u8>) -> Response {
        let mut response = ([(header::CONTENT_TYPE, "image/png")], Body::from(png)).into_response();
        self.headers(&mut response);
        response
    }
}

async fn page() -> Html<&'static str> {
    Html(PAGE)
}

async fn health(State(state): State<Shared>) -> Response {
    json_response(&json!({ "status": "serving", "sites": state.sites.len() }))
}

async fn metrics(State(state): State<Shared>) -> Response {
    let handles: Vec<SiteHandle> = state.sites.values().cloned().collect();
    (
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        state.metrics.render(&handles),
    )
        .into_response()
}

fn counts_json(c: &MapCounts) -> Value {
    json!({
        "sessions": c.sessions,
        "open_sessions": c.open_sessions,
        "dropped_sessions": c.dropped_sessions,
        "nodes": c.nodes,
        "submaps": c.submaps,
        "finished_submaps": c.finished_submaps,
        "trimmed_submaps": c.trimmed_submaps,
        "constraints": c.constraints,
        "loop_closures": c.loop_closures,
    })
}

fn site_json(state: &ConsoleState, handle: &SiteHandle) -> Value {
    let info = handle.current();
    json!({
        "site": handle.site(),
        "version": info.version,
        "landed_at_ms": state.landed_at(handle.site(), info.version),
        "counts": counts_json(&info.counts),
        "loaded": handle.is_loaded(),
    })
}

async fn sites(State(state): State<Shared>) -> Response {
    let list: Vec<Value> = state.sites.values().map(|h| site_json(&state, h)).collect();
    json_response(&json!(list))
}

async fn site(
    State(state): State<Shared>,
    Path(site): Path<String>,
) -> Result<Response, ConsoleError> {
    let handle = state.site(&site)?;
    Ok(json_response(&site_json(&state, handle)))
}

async fn versions(
    State(state): State<Shared>,
    Path(site): Path<String>,
) -> Result<Response, ConsoleError> {
    // The history is the map's: an unloaded site is restored first.
    let view = state.site(&site)?.loaded_view().await?;
    let list: Vec<Value> = view
        .history
        .iter()
        .map(|entry| {
            json!({
                "version": entry.version,
                "landed_at_ms": state.landed_at(&site, entry.version),
                "counts": counts_json(&entry.counts),
            })
        })
        .collect();
    Ok(json_response(&json!({
        "site": site,
        "current_version": view.version,
        "versions": list,
    })))
}

fn pose_json(pose: &Rigid2) -> Value {
    json!({
        "x": pose.translation.vector.x,
        "y": pose.translation.vector.y,
        "theta": pose.theta(),
    })
}

fn session_json(view: &SessionView) -> Value {
    let points: Vec<[f64; 2]> = view
        .trajectory_poses
        .iter()
        .map(|p| [p.translation.vector.x, p.translation.vector.y])
        .collect();
    json!({
        "session": view.session,
        "robot_id": view.robot_id,
        "trajectory": view.trajectory,
        "closed": view.closed,
        "nodes": view.nodes,
        "state": view.state,
        "prior_from_robot": view.prior_from_robot,
        "robot_prior_revoked": view.robot_prior_revoked,
        "global_from_local": view.global_from_local.as_ref().map(pose_json),
        "latest_pose": view.latest_pose.as_ref().map(pose_json),
        "trajectory_xy": points,
    })
}

async fn sessions(
    State(state): State<Shared>,
    Path(site): Path<String>,
) -> Result<Response, ConsoleError> {
    // The trajectories are the map's: an unloaded site is restored first.
    let view = state.site(&site)?.loaded_view().await?;
    Ok(json_response(&json!({
        "site": site,
        "version": view.version,
        "sessions": view.sessions.iter().map(session_json).collect::<Vec<_>>(),
    })))
}

async fn robots(
    State(state): State<Shared>,
    Path(site): Path<String>,
) -> Result<Response, ConsoleError> {
    let views = state.site(&site)?.sessions();
    // Sessions come in the order they were opened: a robot's last one is its latest.
    let mut latest: std::collections::BTreeMap<&str, &SessionView> =
        std::collections::BTreeMap::new();
    for view in views.iter() {
        latest.insert(view.robot_id.as_str(), view);
    }
    let list: Vec<Value> = latest
        .values()
        .map(|v| {
            json!({
                "robot_id": v.robot_id,
                "session": v.session,
                "state": v.state,
                "active": !v.closed,
                "pose": v.latest_pose.as_ref().map(pose_json),
            })
        })
        .collect();
    Ok(json_response(&json!({ "site": site, "robots": list })))
}

/// The `version` parameter (default: the newest).
fn version_param(uri: &Uri, name: &str) -> Result<Option<u64>, ConsoleError> {
    match uri.query().and_then(|q| query_param(q, name)) {
        None => Ok(None),
        Some(text) => text.parse().map(Some).map_err(|_| {
            ConsoleError::BadRequest(format!("{name} must be a version number, got {text:?}"))
        }),
    }
}

/// The history entry of `site`'s map at `version` (default the newest); an unloaded site is restored
/// first.
async fn entry_at(handle: &SiteHandle, version: Option<u64>) -> Result<HistoryEntry, ConsoleError> {
    let view = handle.loaded_view().await?;
    let asked = version.unwrap_or(u64::MAX);
    view.map_at(asked)
        .cloned()
        .ok_or_else(|| ConsoleError::NoMap {
            site: handle.site().to_owned(),
            version: version.unwrap_or(view.version),
        })
}

async fn map_image(
    state: &Shared,
    site: &str,
    version: Option<u64>,
) -> Result<Arc<MapImage>, ConsoleError> {
    let handle = state.site(site)?;
    let entry = entry_at(handle, version).await?;
    state
        .map_image(site, entry)
        .await
        .ok_or_else(|| ConsoleError::Internal("the map could not be rendered".into()))
}

fn placement_json(p: &ImagePlacement) -> Value {
    json!({
        "resolution": p.resolution,
        "origin": p.origin,
        "width": p.width,
        "height": p.height,
    })
}

async fn map_info(
    State(state): State<Shared>,
    Path(site): Path<String>,
    uri: Uri,
) -> Result<Response, ConsoleError> {
    let version = version_param(&uri, "version")?;
    let image = map_image(&state, &site, version).await?;
    Ok(json_response(&json!({
        "site": site,
        "map_version": image.map_version,
        "counts": state.site(&site)?.history().iter()
            .find(|(v, _)| *v == image.map_version)
            .map(|(_, c)| counts_json(c)),
        "landed_at_ms": state.landed_at(&site, image.map_version),
        "image": format!("/api/sites/{site}/map.png?version={}", image.map_version),
        "placement": placement_json(&image.placement),
    })))
}

async fn map_png(
    State(state): State<Shared>,
    Path(site): Path<String>,
    uri: Uri,
    headers: HeaderMap,
) -> Result<Response, ConsoleError> {
    let version = version_param(&uri, "version")?;
    let entry = entry_at(state.site(&site)?, version).await?;
    let answer = PngAnswer {
        etag: image_etag("map", entry.version, entry.version, state.resolution),
        versioned: version.is_some(),
        map_version: entry.version,
    };
    // Answered before rendering: the tag names the map without drawing it.
    if let Some(response) = answer.not_modified(&headers) {
        return Ok(response);
    }
    let image = state
        .map_image(&site, entry)
        .await
        .ok_or_else(|| ConsoleError::Internal("the map could not be rendered".into()))?;
    Ok(answer.png(image.png.clone()))
}

async fn change_image(
    state: &Shared,
    site: &str,
    uri: &Uri,
) -> Result<Arc<ChangeImage>, ConsoleError> {
    let handle = state.site(site)?;
    let from = version_param(uri, "from")?
        .ok_or_else(|| ConsoleError::BadRequest("from=<version> is required".into()))?;
    let to = version_param(uri, "to")?;
    if to.is_some_and(|to| to < from) {
        return Err(ConsoleError::BadRequest("from must not be after to".into()));
    }
    let before = entry_at(handle, Some(from)).await?;
    let after = entry_at(handle, to).await?;
    if let Some(image) = state.cached_change(site, before.version, after.version) {
        return Ok(image);
    }
    let resolution = state.resolution;
    let image =
        tokio::task::spawn_blocking(move || render_change_image(&before, &after, resolution))
            .await
            .map_err(ConsoleError::Worker)?
            .ok_or_else(|| ConsoleError::Internal("the change could not be rendered".into()))?;
    let image = Arc::new(image);
    state.cache_change(site, Arc::clone(&image));
    Ok(image)
}

async fn change_info(
    State(state): State<Shared>,
    Path(site): Path<String>,
    uri: Uri,
) -> Result<Response, ConsoleError> {
    let image = change_image(&state, &site, &uri).await?;
    Ok(json_response(&json!({
        "site": site,
        "from_map_version": image.from_map_version,
        "to_map_version": image.to_map_version,
        "rate": image.rate,
        "unchanged": image.unchanged,
        "removed": image.removed,
        "added": image.added,
        "image": format!(
            "/api/sites/{site}/change.png?from={}&to={}",
            image.from_map_version, image.to_map_version
        ),
        "placement": placement_json(&image.placement),
    })))
}

async fn change_png(
    State(state): State<Shared>,
    Path(site): Path<String>,
    uri: Uri,
    headers: HeaderMap,
) -> Result<Response, ConsoleError> {
    let image = change_image(&state, &site, &uri).await?;
    let answer = PngAnswer {
        etag: image_etag(
            "change",
            image.from_map_version,
            image.to_map_version,
            state.resolution,
        ),
        versioned: version_param(&uri, "to")?.is_some(),
        map_version: image.to_map_version,
    };
    if let Some(response) = answer.not_modified(&headers) {
        return Ok(response);
    }
    Ok(answer.png(image.png.clone()))
}

/// Server-sent events: `version` (a [`super::VersionEvent`]) whenever a site publishes a new version,
/// `site` (a [`super::LoadEvent`]) whenever a site's map leaves memory or comes back. A stream too slow
/// to keep up skips versions (the next event carries the newest).
async fn events(
    State(state): State<Shared>,
) -> Sse<impl tokio_stream::Stream<Item = Result<Event, Infallible>>> {
    let versions = BroadcastStream::new(state.subscribe()).filter_map(|event| {
        let event = event.ok()?;
        let data = serde_json::to_string(&event).ok()?;
        Some(Ok(Event::default().event("version").data(data)))
    });
    let loads = BroadcastStream::new(state.subscribe_loads()).filter_map(|event| {
        let event = event.ok()?;
        let data = serde_json::to_string(&event).ok()?;
        Some(Ok(Event::default().event("site").data(data)))
    });
    Sse::new(versions.merge(loads)).keep_alive(KeepAlive::default())
}

#[cfg(test)]
mod tests;

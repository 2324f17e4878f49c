use std::collections::BTreeMap;

use axum::body::to_bytes;
use axum::http::Request as HttpRequest;
use mapping::geometry::rigid2;
use mapping::grid::{CellIndex, MapLimits, ProbabilityGrid};
use mapping::lifelong::LifelongOptions;
use mapping::sensor::Timestamp;
use nalgebra::{Point2, Vector2};
use proto::{NodeAdded, UploadBatch, UploadItem};
use storage::{MapStore, MemStore};
use tokio_stream::StreamExt as _;
use tower::ServiceExt as _;

use super::*;
use crate::ServerMetrics;
use crate::console::HttpConfig;
use crate::site::{SiteTask, SiteTaskOptions};

const TOKEN: &str = "operator-secret";

fn wall_grid() -> ProbabilityGrid {
    let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(-1.0, -1.0), 40, 40));
    for iy in 0..40 {
        for ix in 0..40 {
            let p = if iy == 30 { 0.9 } else { 0.2 };
            grid.set_probability(&CellIndex::new(ix, iy), p);
        }
    }
    grid
}

fn node(i: u32) -> UploadItem {
    UploadItem::NodeAdded(NodeAdded {
        time: Timestamp(i64::from(i) * 100_000_000),
        local_pose: rigid2(0.1 * f64::from(i), 0.0, 0.0),
        points: vec![Point2::new(1.0, 0.5), Point2::new(1.0, -0.5)],
        insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0))],
        recovered: false,
    })
}

/// A console over one site `s` (operator token [`TOKEN`] unless `open`); with `mapped`, robot `r` has
/// mapped it: one session of 3 nodes and one finished submap, ended.
async fn console(open: bool, mapped: bool) -> (Router, Arc<ConsoleState>) {
    let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
    let metrics = Arc::new(ServerMetrics::default());
    let (site, _task) = SiteTask::spawn(
        "s",
        LifelongOptions::default(),
        store,
        Arc::clone(&metrics),
        SiteTaskOptions::default(),
    )
    .await
    .unwrap();
    if mapped {
        site.open_session("r", "session-a").await.unwrap();
        let items = vec![
            node(0),
            node(1),
            node(2),
            UploadItem::SubmapFinished {
                index: 0,
                grid: wall_grid(),
            },
            UploadItem::SessionEnd,
        ];
        site.upload(UploadBatch {
            site: "s".into(),
            robot_id: "r".into(),
            session_uuid: "session-a".into(),
            seq: 1,
            items,
        })
        .await
        .unwrap();
    }
    let config = HttpConfig {
        operator_token: (!open).then(|| TOKEN.to_owned()),
        ..HttpConfig::default()
    };
    let sites = Arc::new(BTreeMap::from([("s".to_owned(), site)]));
    let state = Arc::new(ConsoleState::new(&config, sites, metrics));
    (router(Arc::clone(&state)), state)
}

async fn get(app: &Router, uri: &str, token: Option<&str>) -> (StatusCode, Response) {
    let mut request = HttpRequest::builder().uri(uri);
    if let Some(token) = token {
        request = request.header(header::AUTHORIZATION, format!("Bearer {token}"));
    }
    let response = app
        .clone()
        .oneshot(request.body(Body::empty()).unwrap())
        .await
        .unwrap();
    (response.status(), response)
}

async fn body(response: Response) -> Vec<u8> {
    to_bytes(response.into_body(), 1 << 26)
        .await
        .unwrap()
        .to_vec()
}

async fn get_json(app: &Router, uri: &str) -> Value {
    let (status, response) = get(app, uri, Some(TOKEN)).await;
    let bytes = body(response).await;
    assert_eq!(
        status,
        StatusCode::OK,
        "{uri}: {}",
        String::from_utf8_lossy(&bytes)
    );
    serde_json::from_slice(&bytes).unwrap()
}

async fn get_text(app: &Router, uri: &str) -> String {
    let (status, response) = get(app, uri, Some(TOKEN)).await;
    assert_eq!(status, StatusCode::OK, "{uri}");
    String::from_utf8(body(response).await).unwrap()
}

#[tokio::test]
async fn without_the_operator_token_everything_but_health_is_refused() {
    let (app, _) = console(false, true).await;
    for uri in [
        "/",
        "/metrics",
        "/api/sites",
        "/api/sites/s",
        "/api/sites/s/sessions",
        "/api/sites/s/map.png",
        "/api/events",
    ] {
        let (status, response) = get(&app, uri, None).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{uri}");
        assert!(response.headers().contains_key(header::WWW_AUTHENTICATE));
        let error: Value = serde_json::from_slice(&body(response).await).unwrap();
        assert!(
            error["error"].as_str().unwrap().contains("operator token"),
            "{error}"
        );
        let (status, _) = get(&app, uri, Some("robot-token")).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{uri} with a wrong token");
    }
    let (status, response) = get(&app, "/health", None).await;
    assert_eq!(status, StatusCode::OK);
    let health: Value = serde_json::from_slice(&body(response).await).unwrap();
    assert_eq!(health, json!({ "status": "serving", "sites": 1 }));
}

#[tokio::test]
async fn the_token_in_the_query_opens_the_page_and_sets_the_cookie() {
    let (app, _) = console(false, false).await;
    let (status, response) = get(&app, &format!("/?token={TOKEN}"), None).await;
    assert_eq!(status, StatusCode::OK);
    let cookie = response.headers()[header::SET_COOKIE]
        .to_str()
        .unwrap()
        .to_owned();
    assert!(cookie.starts_with(&format!("{COOKIE}={TOKEN}")), "{cookie}");
    let page = String::from_utf8(body(response).await).unwrap();
    assert!(page.contains("evermap console") && page.contains("EventSource"));
    // The page's own requests carry the cookie.
    let request = HttpRequest::builder()
        .uri("/api/sites")
        .header(header::COOKIE, format!("{COOKIE}={TOKEN}"))
        .body(Body::empty())
        .unwrap();
    assert_eq!(app.oneshot(request).await.unwrap().status(), StatusCode::OK);
}

const COOKIE: &str = crate::console::COOKIE_NAME;

#[tokio::test]
async fn an_open_console_needs_no_token() {
    let (app, _) = console(true, false).await;
    let (status, _) = get(&app, "/api/sites", None).await;
    assert_eq!(status, StatusCode::OK);
}

#[tokio::test]
async fn sites_list_their_version_and_counts() {
    let (app, state) = console(false, true).await;
    let version = state.site("s").unwrap().current().version;
    assert_eq!(version, 2, "the open and the upload");
    state.landed("s", version, MapCounts::default());
    let sites = get_json(&app, "/api/sites").await;
    let list = sites.as_array().unwrap();
    assert_eq!(list.len(), 1);
    assert_eq!(list[0]["site"], "s");
    assert_eq!(list[0]["version"], 2);
    assert!(list[0]["landed_at_ms"].as_u64().unwrap() > 1_700_000_000_000);
    assert_eq!(list[0]["counts"]["sessions"], 1);
    assert_eq!(list[0]["counts"]["finished_submaps"], 1);
    assert_eq!(list[0]["counts"]["nodes"], 3);
    assert_eq!(get_json(&app, "/api/sites/s").await, list[0]);
}

#[tokio::test]
async fn an_unknown_site_or_route_is_404_and_a_bad_version_400() {
    let (app, _) = console(false, true).await;
    for uri in [
        "/api/sites/nope",
        "/api/sites/nope/sessions",
        "/api/sites/nope/versions",
        "/api/sites/nope/robots",
        "/api/sites/nope/map",
        "/api/sites/nope/map.png",
        "/api/sites/nope/change?from=1",
        "/api/nothing",
    ] {
        let (status, response) = get(&app, uri, Some(TOKEN)).await;
        assert_eq!(status, StatusCode::NOT_FOUND, "{uri}");
        let error: Value = serde_json::from_slice(&body(response).await).unwrap();
        assert!(error["error"].is_string(), "{uri}: {error}");
    }
    let (status, _) = get(&app, "/api/sites/s/map?version=abc", Some(TOKEN)).await;
    assert_eq!(status, StatusCode::BAD_REQUEST);
    let (status, _) = get(&app, "/api/sites/s/change", Some(TOKEN)).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "from is required");
    let (status, _) = get(&app, "/api/sites/s/change?from=5&to=2", Some(TOKEN)).await;
    assert_eq!(status, StatusCode::BAD_REQUEST);
    let (status, _) = get(&app, "/api/sites/s/map?version=1", Some(TOKEN)).await;
    assert_eq!(
        status,
        StatusCode::NOT_FOUND,
        "no map at version 1 (the open)"
    );
}

#[tokio::test]
async fn a_site_without_a_map_answers_404_for_its_image() {
    let (app, _) = console(false, false).await;
    let (status, _) = get(&app, "/api/sites/s/map.png", Some(TOKEN)).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    let versions = get_json(&app, "/api/sites/s/versions").await;
    assert_eq!(versions["versions"], json!([]));
}

#[tokio::test]
async fn the_map_its_history_sessions_and_robots_are_served() {
    let (app, _) = console(false, true).await;
    let versions = get_json(&app, "/api/sites/s/versions").await;
    assert_eq!(versions["current_version"], 2);
    assert_eq!(versions["versions"][0]["version"], 2);
    assert_eq!(versions["versions"][0]["counts"]["finished_submaps"], 1);

    let info = get_json(&app, "/api/sites/s/map").await;
    assert_eq!(info["map_version"], 2);
    assert_eq!(info["image"], "/api/sites/s/map.png?version=2");
    assert_eq!(info["placement"]["width"], 40);
    assert!((info["placement"]["origin"][0].as_f64().unwrap() + 1.0).abs() < 1e-9);
    let (status, response) = get(&app, "/api/sites/s/map.png?version=2", Some(TOKEN)).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(response.headers()[header::CONTENT_TYPE], "image/png");
    assert_eq!(response.headers()["x-evermap-map-version"], "2");
    assert_eq!(&body(response).await[1..4], b"PNG");

    let change = get_json(&app, "/api/sites/s/change?from=2").await;
    assert_eq!(change["from_map_version"], 2);
    assert_eq!(change["to_map_version"], 2);
    assert_eq!(change["removed"], 0);
    assert_eq!(change["added"], 0);
    assert!(change["unchanged"].as_u64().unwrap() > 0, "{change}");
    let (status, response) = get(&app, "/api/sites/s/change.png?from=2", Some(TOKEN)).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(&body(response).await[1..4], b"PNG");

    let sessions = get_json(&app, "/api/sites/s/sessions").await;
    let session = &sessions["sessions"][0];
    assert_eq!(session["session"], "session-a");
    assert_eq!(session["robot_id"], "r");
    assert_eq!(session["state"], "base");
    assert_eq!(session["closed"], true);
    assert_eq!(session["nodes"], 3);
    assert_eq!(session["trajectory_xy"].as_array().unwrap().len(), 3);
    assert!(
        (session["latest_pose"]["x"].as_f64().unwrap() - 0.2).abs() < 1e-3,
        "{session}"
    );

    let robots = get_json(&app, "/api/sites/s/robots").await;
    assert_eq!(robots["robots"][0]["robot_id"], "r");
    assert_eq!(robots["robots"][0]["active"], false);
    assert_eq!(robots["robots"][0]["pose"], session["latest_pose"]);
}

#[tokio::test]
async fn a_new_version_reaches_the_event_stream() {
    let (app, state) = console(false, false).await;
    let watchers = state.watch_versions();
    let (status, response) = get(&app, "/api/events", Some(TOKEN)).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(
        response.headers()[header::CONTENT_TYPE],
        "text/event-stream"
    );
    let mut stream = response.into_body().into_data_stream();
    state
        .site("s")
        .unwrap()
        .open_session("r", "session-b")
        .await
        .unwrap();
    let (name, data) = next_event(&mut stream).await;
    assert_eq!(name, "version", "{data}");
    assert_eq!(data["site"], "s");
    assert_eq!(data["version"], 1);
    assert_eq!(data["open_sessions"], 1);
    assert!(state.landed_at("s", 1).is_some());
    for w in watchers {
        w.abort();
    }
}

/// The next event of an SSE body (`event: <name>` then `data: <json>`, within 10 s): its name and its
/// data.
async fn next_event(
    stream: &mut (impl tokio_stream::Stream<Item = Result<axum::body::Bytes, axum::Error>> + Unpin),
) -> (String, Value) {
    let chunk = tokio::time::timeout(std::time::Duration::from_secs(10), stream.next())
        .await
        .expect("an event within 10 s")
        .unwrap()
        .unwrap();
    let text = String::from_utf8(chunk.to_vec()).unwrap();
    let mut lines = text.lines();
    let name = lines
        .next()
        .and_then(|line| line.strip_prefix("event: "))
        .unwrap_or_else(|| panic!("no event line: {text}"))
        .to_owned();
    let data = lines
        .next()
        .and_then(|line| line.strip_prefix("data: "))
        .unwrap_or_else(|| panic!("no data line: {text}"));
    (name, serde_json::from_str(data).unwrap())
}

// Reference: issue 34 item 4 — the console shows loaded and unloaded sites, live.
#[tokio::test]
async fn a_site_leaving_memory_and_coming_back_reaches_the_event_stream() {
    let (app, state) = console(false, true).await;
    let watchers = state.watch_versions();
    let (status, response) = get(&app, "/api/events", Some(TOKEN)).await;
    assert_eq!(status, StatusCode::OK);
    let mut stream = response.into_body().into_data_stream();
    let site = state.site("s").unwrap().clone();
    assert!(site.unload().await.unwrap());
    let (name, data) = next_event(&mut stream).await;
    assert_eq!(name, "site");
    assert_eq!(data, json!({ "site": "s", "loaded": false }));
    site.node_poses().await.unwrap();
    let (name, data) = next_event(&mut stream).await;
    assert_eq!(name, "site", "a restore is no new version: {data}");
    assert_eq!(data, json!({ "site": "s", "loaded": true }));
    for w in watchers {
        w.abort();
    }
}

#[tokio::test]
async fn images_carry_an_entity_tag_and_a_held_one_is_not_sent_again() {
    let (app, _) = console(false, true).await;
    let request = |uri: &str, tag: Option<&str>| {
        let mut request = HttpRequest::builder()
            .uri(uri)
            .header(header::AUTHORIZATION, format!("Bearer {TOKEN}"));
        if let Some(tag) = tag {
            request = request.header(header::IF_NONE_MATCH, tag);
        }
        app.clone().oneshot(request.body(Body::empty()).unwrap())
    };
    // Asked by version: cacheable for good.
    let response = request("/api/sites/s/map.png?version=2", None)
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let tag = response.headers()[header::ETAG]
        .to_str()
        .unwrap()
        .to_owned();
    assert!(tag.starts_with("\"map-2-2-") && tag.ends_with('"'), "{tag}");
    let cache = response.headers()[header::CACHE_CONTROL].to_str().unwrap();
    assert!(cache.contains("max-age"), "{cache}");
    // Asked as "now": revalidated every time, with the same tag while the map is the same.
    let response = request("/api/sites/s/map.png", None).await.unwrap();
    assert_eq!(response.headers()[header::ETAG], tag.as_str());
    assert_eq!(
        response.headers()[header::CACHE_CONTROL],
        "private, no-cache"
    );
    let png = body(response).await;
    assert_eq!(&png[1..4], b"PNG");
    for uri in ["/api/sites/s/map.png", "/api/sites/s/map.png?version=2"] {
        let held = format!("\"other\", W/{tag}");
        let response = request(uri, Some(&held)).await.unwrap();
        assert_eq!(response.status(), StatusCode::NOT_MODIFIED, "{uri}");
        assert_eq!(response.headers()[header::ETAG], tag.as_str());
        assert!(body(response).await.is_empty());
        let response = request(uri, Some("\"map-1-1-50000um\"")).await.unwrap();
        assert_eq!(response.status(), StatusCode::OK, "{uri} with a stale tag");
        assert_eq!(body(response).await, png);
    }
    // The change image the same way.
    let response = request("/api/sites/s/change.png?from=2&to=2", None)
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::OK);
    let tag = response.headers()[header::ETAG]
        .to_str()
        .unwrap()
        .to_owned();
    assert!(tag.starts_with("\"change-2-2-"), "{tag}");
    let response = request("/api/sites/s/change.png?from=2&to=2", Some(&tag))
        .await
        .unwrap();
    assert_eq!(response.status(), StatusCode::NOT_MODIFIED);
}

// Reference: issue 34 item 4 — "metrics and the console show loaded and unloaded sites"; the map
// waits for the restore.
#[tokio::test]
async fn an_unloaded_site_is_listed_as_such_and_its_map_restores_it() {
    let (app, state) = console(false, true).await;
    let site = state.site("s").unwrap().clone();
    assert_eq!(get_json(&app, "/api/sites").await[0]["loaded"], true);
    assert!(site.unload().await.unwrap());
    let listed = get_json(&app, "/api/sites").await;
    assert_eq!(listed[0]["loaded"], false);
    assert_eq!(listed[0]["version"], 2);
    assert_eq!(listed[0]["counts"]["nodes"], 3);
    let metrics = get_text(&app, "/metrics").await;
    assert!(metrics.contains("evermap_sites_unloaded 1\n"), "{metrics}");
    assert!(
        metrics.contains("evermap_site_loaded{site=\"s\"} 0\n"),
        "{metrics}"
    );
    // Where the robots are is answered without the map.
    let robots = get_json(&app, "/api/sites/s/robots").await;
    assert_eq!(robots["robots"][0]["robot_id"], "r");
    assert!(!site.is_loaded());
    // The map is the map's: it waits for the restore.
    let info = get_json(&app, "/api/sites/s/map").await;
    assert_eq!(info["map_version"], 2);
    assert!(site.is_loaded());
    assert_eq!(get_json(&app, "/api/sites").await[0]["loaded"], true);
    // So are the trajectories and the history.
    assert!(site.unload().await.unwrap());
    let sessions = get_json(&app, "/api/sites/s/sessions").await;
    assert_eq!(
        sessions["sessions"][0]["trajectory_xy"]
            .as_array()
            .unwrap()
            .len(),
        3
    );
    assert!(site.unload().await.unwrap());
    let versions = get_json(&app, "/api/sites/s/versions").await;
    assert_eq!(versions["versions"][0]["version"], 2);
    let metrics = get_text(&app, "/metrics").await;
    assert!(metrics.contains("evermap_sites_loaded 1\n"), "{metrics}");
    assert!(
        metrics.contains("evermap_site_unloads_total 3\n"),
        "{metrics}"
    );
    assert!(
        metrics.contains("evermap_site_restore_seconds_count 3\n"),
        "{metrics}"
    );
}

//! In-place recovery after a full disk that wedges the store (issue 16 §1): the server's store behaves
//! as sled does on a real full disk (`storage::DiskFullStore` with `FailAt::Wedge`, measured on a tmpfs
//! in `storage/tests/disk_full_tmpfs.rs`): a change is applied but its flush fails, after which the store
//! refuses every write until it is reopened, and the reopen loses what was never flushed. The same
//! server process — no restart — refuses clearly while the disk is full, publishes nothing that is not
//! durable, and once space returns the store reopens itself, the site task rebuilds its map from the
//! store's log, and the robot's retries land exactly once: the log holds each batch once, the map equals
//! an uninterrupted run's, the published versions never went backwards, and a restart replays the same.
//! The same on a real tmpfs: `tests/tests/disk_full_tmpfs_fleet.rs` (needs root). Every wait is bounded.

use std::sync::{Arc, Mutex};

use prost::Message as _;
use proto::pb;
use server::RunningServer;
use server::site::SITE_LOG_KIND;
use storage::{DiskFullStore, FailAt, MapStore, MemStore};
use tests::OneRobotSite;

const SITE: &str = "store-wedged";
const TOKEN: &str = "token-wedged-r1";

const FIXTURE: OneRobotSite = OneRobotSite {
    site: SITE,
    token: TOKEN,
};

/// The sequence numbers of the uploads in the site's log, in log order.
fn logged_seqs(store: &dyn MapStore) -> Vec<u64> {
    store
        .scan(SITE, SITE_LOG_KIND)
        .expect("scan")
        .filter_map(|record| {
            let (_, bytes) = record.expect("record");
            match pb::SiteLogEntry::decode(bytes.as_slice())
                .expect("entry")
                .entry
            {
                Some(pb::site_log_entry::Entry::Upload(upload)) => Some(upload.seq),
                _ => None,
            }
        })
        .collect()
}

// Reference: issue 16 §1 "disk full ... a clear error, no corrupt record, recovery once space returns",
// in place (no restart) with sled's wedged-until-reopened store.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_wedged_by_a_full_disk_recovers_in_place_and_nothing_is_lost_or_doubled() {
    let expected = FIXTURE.uninterrupted().await;
    let disk = Arc::new(DiskFullStore::new(Arc::new(MemStore::new()), FailAt::Wedge));
    let store = Arc::clone(&disk) as Arc<dyn MapStore>;
    let server = RunningServer::start(&FIXTURE.config(), Arc::clone(&store))
        .await
        .expect("server");
    let site = server.site(SITE).expect("site").clone();
    // Every version the site publishes, in order.
    let published = Arc::new(Mutex::new(vec![site.current().version]));
    let mut versions = site.subscribe();
    let watcher = {
        let published = Arc::clone(&published);
        tokio::spawn(async move {
            while versions.changed().await.is_ok() {
                let version = versions.borrow_and_update().version;
                published.lock().expect("lock").push(version);
            }
        })
    };
    let mut robot = FIXTURE.uploader(&server, "s-1");
    OneRobotSite::deliver_first_nodes(&mut robot).await;
    let before = site.current();

    disk.fill();
    OneRobotSite::expect_full_disk_refusals(&mut robot, "in place").await;
    assert!(disk.is_wedged(), "a failed flush wedges the store");
    assert_eq!(
        site.current(),
        before,
        "nothing published that is not durable"
    );

    // Space returns: the same server recovers (bounded retries, as the robot's would be).
    disk.free();
    robot.enqueue(&OneRobotSite::node(5)).expect("enqueue");
    let mut refusals = 0;
    for attempt in 1..=5 {
        match robot.flush().await {
            Ok(_) => break,
            Err(e) => {
                assert!(e.is_transient(), "{e}");
                assert!(attempt < 5, "never recovered: {e}");
                refusals += 1;
            }
        }
    }
    assert_eq!(disk.generation(), 1, "the store reopened once");
    assert!(robot.outbox().is_empty().expect("empty"));
    assert_eq!(
        logged_seqs(store.as_ref()),
        [1, 2, 3, 4, 5],
        "every batch stored exactly once (batch 3, applied before the wedge, was lost by the reopen)"
    );
    let served = site.node_poses().await.expect("poses");
    assert_eq!(served, expected, "the same map as without faults");
    let version = site.current().version;
    assert_eq!(version, 6, "one open and five uploads");
    server.shutdown().await.expect("shutdown");
    watcher.await.expect("watcher");
    let published = published.lock().expect("lock").clone();
    assert!(
        published.windows(2).all(|w| w[0] <= w[1]),
        "published versions went backwards: {published:?}"
    );
    assert_eq!(published.last(), Some(&version));
    eprintln!(
        "in place: {refusals} retryable refusals after space returned, published {published:?}"
    );

    // A restart replays the store's log to the same map.
    let server = RunningServer::start(&FIXTURE.config(), store)
        .await
        .expect("restart");
    let site = server.site(SITE).expect("site");
    assert_eq!(site.current().version, version);
    assert_eq!(
        site.node_poses().await.expect("poses"),
        expected,
        "replayed"
    );
    server.shutdown().await.expect("shutdown");
}

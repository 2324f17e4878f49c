//! Disk full on the server (issue 16 §1): the server's sled store, behind `storage::DiskFullStore`,
//! runs out of space mid-session — the write failing outright, or applied but not flushable (what sled
//! does when its flush hits the full disk). The robot gets a clear, retryable refusal naming the full
//! disk, nothing is acknowledged or published that is not durable, and once space returns the robot's
//! retries land exactly once; a restart then replays a log without a corrupt record to the same map as
//! an uninterrupted run. (Injected rather than a real full filesystem: mounting a size-limited one needs
//! privileges CI may lack; see `storage::DiskFullStore`.) Every wait is bounded.

use std::sync::Arc;

use server::RunningServer;
use storage::{DiskFullStore, FailAt, MapStore, SledStore, SledStoreOptions};
use tests::OneRobotSite;

const SITE: &str = "store-full";
const TOKEN: &str = "token-full-r1";

const FIXTURE: OneRobotSite = OneRobotSite {
    site: SITE,
    token: TOKEN,
};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_is_a_clear_retryable_refusal_and_nothing_is_lost_or_doubled() {
    let expected = FIXTURE.uninterrupted().await;
    for fail_at in [FailAt::Apply, FailAt::Flush] {
        let dir = tempfile::tempdir().expect("tempdir");
        let sled: Arc<dyn MapStore> =
            Arc::new(SledStore::open(&SledStoreOptions::at(dir.path())).expect("sled"));
        let disk = Arc::new(DiskFullStore::new(sled, fail_at));
        let server =
            RunningServer::start(&FIXTURE.config(), Arc::clone(&disk) as Arc<dyn MapStore>)
                .await
                .expect("server");
        let site = server.site(SITE).expect("site").clone();
        let mut robot = FIXTURE.uploader(&server, "s-1");
        OneRobotSite::deliver_first_nodes(&mut robot).await;
        let before = site.current();

        disk.fill();
        OneRobotSite::expect_full_disk_refusals(&mut robot, &format!("{fail_at:?}")).await;
        assert!(disk.failures() >= 3, "{fail_at:?}");
        assert_eq!(
            site.current(),
            before,
            "{fail_at:?}: nothing published that is not durable"
        );
        assert_eq!(robot.outbox().len().expect("len"), 2, "{fail_at:?}");

        disk.free();
        robot.enqueue(&OneRobotSite::node(5)).expect("enqueue");
        let stats = robot.flush().await.expect("flush once space returns");
        // Batch 3, stored but not flushable, is acknowledged (as already applied) once it is flushed,
        // never applied twice.
        let stored_before = usize::from(fail_at == FailAt::Flush);
        assert_eq!(
            (stats.applied, stats.already_acked + stats.duplicates),
            (3 - stored_before, stored_before),
            "{fail_at:?}: {stats:?}"
        );
        assert!(robot.outbox().is_empty().expect("empty"), "{fail_at:?}");
        let version = site.current().version;
        let served = site.node_poses().await.expect("poses");
        assert_eq!(
            served, expected,
            "{fail_at:?}: the same map as without faults"
        );
        server.shutdown().await.expect("shutdown");
        drop(site);
        drop(disk);

        // A restart replays every stored record (each CRC-checked, in sequence) to the same map.
        let sled: Arc<dyn MapStore> =
            Arc::new(SledStore::open(&SledStoreOptions::at(dir.path())).expect("reopen"));
        let server = RunningServer::start(&FIXTURE.config(), sled)
            .await
            .expect("restart");
        let site = server.site(SITE).expect("site");
        assert_eq!(site.current().version, version, "{fail_at:?}");
        let replayed = site.node_poses().await.expect("poses");
        assert_eq!(replayed, expected, "{fail_at:?}: replayed");
        server.shutdown().await.expect("shutdown");
    }
}

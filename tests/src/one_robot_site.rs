//! A site with one robot (`r1`) on a loopback gRPC server, fed synthetic nodes: the fixture of the
//! full-disk tests, which compare a faulty run's stored map with an uninterrupted one's.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use mapping::geometry::{Rigid2, rigid2};
use mapping::pose_graph::NodeId;
use mapping::sensor::Timestamp;
use nalgebra::Point2;
use proto::{NodeAdded, UploadItem};
use robot_agent::outbox::Outbox;
use robot_agent::uplink::{GrpcUplink, UplinkError, Uploader};
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::MemStore;

/// Node poses of a site, by node.
pub type NodePoses = BTreeMap<NodeId, Rigid2>;

/// A site id and its one robot's token.
#[derive(Clone, Copy, Debug)]
pub struct OneRobotSite {
    /// The site id.
    pub site: &'static str,
    /// Robot `r1`'s bearer token.
    pub token: &'static str,
}

impl OneRobotSite {
    /// Node `i` of a session: 0.1 m per node along x, two points, inserted into submap 0.
    pub fn node(i: i64) -> Vec<UploadItem> {
        vec![UploadItem::NodeAdded(NodeAdded {
            time: Timestamp(i * 100_000_000),
            local_pose: rigid2(0.1 * i as f64, 0.0, 0.0),
            points: vec![Point2::new(1.0, 0.5), Point2::new(2.0, 0.0)],
            insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0))],
            recovered: false,
        })]
    }

    /// A server configuration with this site only, gRPC on an ephemeral loopback port, no metrics.
    pub fn config(&self) -> ServerConfig {
        ServerConfig {
            listen: "127.0.0.1:0".parse().expect("addr"),
            metrics_listen: None,
            sites: vec![SiteConfig {
                id: self.site.into(),
                robots: vec![RobotConfig {
                    id: "r1".into(),
                    token: self.token.into(),
                }],
            }],
            ..ServerConfig::default()
        }
    }

    /// Robot `r1`'s uploader for `session`, over gRPC to `server`, with an in-memory outbox.
    pub fn uploader(&self, server: &RunningServer, session: &str) -> Uploader<GrpcUplink> {
        let url = format!("http://{}", server.grpc_addr());
        let uplink = GrpcUplink::new(
            &url,
            self.site,
            self.token,
            4 << 20,
            Duration::from_secs(10),
        )
        .expect("uplink");
        Uploader::new(
            uplink,
            Outbox::in_memory(self.site),
            self.site,
            "r1",
            session,
        )
        .expect("uploader")
    }

    /// Sends nodes 1 and 2 through `robot` and checks that the server applied both.
    pub async fn deliver_first_nodes(robot: &mut Uploader<GrpcUplink>) {
        robot.enqueue(&Self::node(1)).expect("enqueue");
        robot.enqueue(&Self::node(2)).expect("enqueue");
        assert_eq!(robot.flush().await.expect("flush").applied, 2);
    }

    /// With the server's disk full: queues nodes 3 and 4 and checks that three flushes in a row are
    /// refused as retryable with a message naming the full disk (`case` prefixes the failure messages).
    pub async fn expect_full_disk_refusals(robot: &mut Uploader<GrpcUplink>, case: &str) {
        robot.enqueue(&Self::node(3)).expect("enqueue");
        robot.enqueue(&Self::node(4)).expect("enqueue");
        for _ in 0..3 {
            match robot.flush().await {
                Err(UplinkError::Unavailable { what: message, .. }) => assert!(
                    message.contains("No space left on device"),
                    "{case}: the refusal names the full disk: {message}"
                ),
                other => panic!("{case}: expected a retryable refusal, got {other:?}"),
            }
        }
    }

    /// The node poses of a server fed nodes 1..=5 of one session without faults.
    pub async fn uninterrupted(&self) -> NodePoses {
        let server = RunningServer::start(&self.config(), Arc::new(MemStore::new()))
            .await
            .expect("server");
        let mut robot = self.uploader(&server, "s-1");
        for i in 1..=5 {
            robot.enqueue(&Self::node(i)).expect("enqueue");
        }
        robot.flush().await.expect("flush");
        let poses = server
            .site(self.site)
            .expect("site")
            .node_poses()
            .await
            .expect("poses");
        server.shutdown().await.expect("shutdown");
        poses
    }
}

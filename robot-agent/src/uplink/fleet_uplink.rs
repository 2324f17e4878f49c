//! [`FleetUplink`]: the transport chosen at run time (configuration, command line), one type for the
//! uploader and the site follower whichever it is.

use proto::{MapDelta, pb};

use super::{Acked, GrpcUplink, MapUplink, OpenedSession, UplinkError, VersionStream, ZenohUplink};

/// gRPC or zenoh.
#[derive(Clone)]
pub enum FleetUplink {
    /// Straight to the server over gRPC.
    Grpc(Box<GrpcUplink>),
    /// Through the zenoh network (routers or a direct peer link).
    Zenoh(ZenohUplink),
}

impl FleetUplink {
    /// `grpc` or `zenoh`.
    pub fn transport(&self) -> &'static str {
        match self {
            Self::Grpc(_) => "grpc",
            Self::Zenoh(_) => "zenoh",
        }
    }
}

impl MapUplink for FleetUplink {
    async fn open_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<OpenedSession, UplinkError> {
        match self {
            Self::Grpc(u) => u.open_session(robot_id, session_uuid).await,
            Self::Zenoh(u) => u.open_session(robot_id, session_uuid).await,
        }
    }

    async fn upload(&mut self, batch: &pb::UploadBatch) -> Result<Acked, UplinkError> {
        match self {
            Self::Grpc(u) => u.upload(batch).await,
            Self::Zenoh(u) => u.upload(batch).await,
        }
    }

    async fn close_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<u64, UplinkError> {
        match self {
            Self::Grpc(u) => u.close_session(robot_id, session_uuid).await,
            Self::Zenoh(u) => u.close_session(robot_id, session_uuid).await,
        }
    }

    async fn map_version(&mut self) -> Result<u64, UplinkError> {
        match self {
            Self::Grpc(u) => u.map_version().await,
            Self::Zenoh(u) => u.map_version().await,
        }
    }

    async fn delta_since(&mut self, since: u64) -> Result<MapDelta, UplinkError> {
        match self {
            Self::Grpc(u) => u.delta_since(since).await,
            Self::Zenoh(u) => u.delta_since(since).await,
        }
    }

    async fn watch_versions(&mut self) -> Result<VersionStream, UplinkError> {
        match self {
            Self::Grpc(u) => u.watch_versions().await,
            Self::Zenoh(u) => u.watch_versions().await,
        }
    }
}

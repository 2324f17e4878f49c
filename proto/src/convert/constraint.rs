//! Pose-graph constraints.

use mapping::pose_graph::{Constraint, ConstraintKind, NodeId, RobustLoss, SubmapId, VariableId};
use nalgebra::Matrix3;

use crate::convert::check_finite;
use crate::{ConversionError, FORMAT_VERSION, check_format_version, pb, pose_from_pb, pose_to_pb};

const M: &str = "Constraint";

impl From<NodeId> for pb::NodeId {
    fn from(id: NodeId) -> Self {
        Self {
            trajectory: id.trajectory,
            index: id.index,
        }
    }
}

impl From<pb::NodeId> for NodeId {
    fn from(id: pb::NodeId) -> Self {
        Self {
            trajectory: id.trajectory,
            index: id.index,
        }
    }
}

impl From<SubmapId> for pb::SubmapId {
    fn from(id: SubmapId) -> Self {
        Self {
            trajectory: id.trajectory,
            index: id.index,
        }
    }
}

impl From<pb::SubmapId> for SubmapId {
    fn from(id: pb::SubmapId) -> Self {
        Self {
            trajectory: id.trajectory,
            index: id.index,
        }
    }
}

pub(crate) fn variable_to_pb(id: VariableId) -> pb::VariableRef {
    pb::VariableRef {
        id: Some(match id {
            VariableId::Node(n) => pb::variable_ref::Id::Node(n.into()),
            VariableId::Submap(s) => pb::variable_ref::Id::Submap(s.into()),
        }),
    }
}

fn variable_from_pb(
    v: Option<&pb::VariableRef>,
    field: &'static str,
) -> Result<VariableId, ConversionError> {
    variable_in(v, M, field)
}

/// A variable from the wire: the (optional, message-typed) field `message.field`.
pub(crate) fn variable_in(
    v: Option<&pb::VariableRef>,
    message: &'static str,
    field: &'static str,
) -> Result<VariableId, ConversionError> {
    match v.and_then(|v| v.id) {
        Some(pb::variable_ref::Id::Node(n)) => Ok(VariableId::Node(n.into())),
        Some(pb::variable_ref::Id::Submap(s)) => Ok(VariableId::Submap(s.into())),
        None => Err(ConversionError::MissingField { message, field }),
    }
}

/// The wire form of a robust loss: its kind and its scale.
pub(crate) fn loss_to_pb(loss: RobustLoss) -> (pb::RobustLossKind, f64) {
    match loss {
        RobustLoss::Trivial => (pb::RobustLossKind::Trivial, 0.0),
        RobustLoss::Huber { delta } => (pb::RobustLossKind::Huber, delta),
        RobustLoss::Cauchy { scale } => (pb::RobustLossKind::Cauchy, scale),
        RobustLoss::Dcs { phi } => (pb::RobustLossKind::Dcs, phi),
        RobustLoss::TruncatedLeastSquares { threshold } => {
            (pb::RobustLossKind::TruncatedLeastSquares, threshold)
        }
    }
}

/// The wire form of a constraint kind.
pub(crate) fn kind_to_pb(kind: ConstraintKind) -> pb::ConstraintKind {
    match kind {
        ConstraintKind::NodeToSubmapIntra => pb::ConstraintKind::NodeToSubmapIntra,
        ConstraintKind::NodeToSubmapInter => pb::ConstraintKind::NodeToSubmapInter,
        ConstraintKind::Odometry => pb::ConstraintKind::Odometry,
        ConstraintKind::NodeToNode => pb::ConstraintKind::NodeToNode,
        ConstraintKind::SubmapToSubmap => pb::ConstraintKind::SubmapToSubmap,
    }
}

/// A constraint kind from the wire (`message.kind`).
pub(crate) fn kind_from_pb(
    kind: i32,
    message: &'static str,
) -> Result<ConstraintKind, ConversionError> {
    match pb::ConstraintKind::try_from(kind) {
        Ok(pb::ConstraintKind::NodeToSubmapIntra) => Ok(ConstraintKind::NodeToSubmapIntra),
        Ok(pb::ConstraintKind::NodeToSubmapInter) => Ok(ConstraintKind::NodeToSubmapInter),
        Ok(pb::ConstraintKind::Odometry) => Ok(ConstraintKind::Odometry),
        Ok(pb::ConstraintKind::NodeToNode) => Ok(ConstraintKind::NodeToNode),
        Ok(pb::ConstraintKind::SubmapToSubmap) => Ok(ConstraintKind::SubmapToSubmap),
        _ => Err(ConversionError::OutOfRange {
            message,
            field: "kind",
            value: kind.into(),
            expected: "a known ConstraintKind",
        }),
    }
}

/// A valid robust loss from the wire (`message.loss` and `message.loss_scale`).
pub(crate) fn loss_from_pb(
    loss: i32,
    loss_scale: f64,
    message: &'static str,
) -> Result<RobustLoss, ConversionError> {
    let scale = check_finite(loss_scale, message, "loss_scale")?;
    let loss = match pb::RobustLossKind::try_from(loss) {
        Ok(pb::RobustLossKind::Trivial) => RobustLoss::Trivial,
        Ok(pb::RobustLossKind::Huber) => RobustLoss::Huber { delta: scale },
        Ok(pb::RobustLossKind::Cauchy) => RobustLoss::Cauchy { scale },
        Ok(pb::RobustLossKind::Dcs) => RobustLoss::Dcs { phi: scale },
        Ok(pb::RobustLossKind::TruncatedLeastSquares) => {
            RobustLoss::TruncatedLeastSquares { threshold: scale }
        }
        _ => {
            return Err(ConversionError::OutOfRange {
                message,
                field: "loss",
                value: loss.into(),
                expected: "a known RobustLossKind",
            });
        }
    };
    if !loss.is_valid() {
        return Err(ConversionError::OutOfRange {
            message,
            field: "loss_scale",
            value: scale.into(),
            expected: "positive for this loss",
        });
    }
    Ok(loss)
}

impl From<&Constraint> for pb::Constraint {
    fn from(c: &Constraint) -> Self {
        let i = &c.information;
        let (loss, loss_scale) = loss_to_pb(c.loss);
        Self {
            format_version: FORMAT_VERSION,
            kind: kind_to_pb(c.kind).into(),
            from: Some(variable_to_pb(c.from)),
            to: Some(variable_to_pb(c.to)),
            from_from_to: Some(pose_to_pb(&c.from_from_to)),
            information: vec![
                i[(0, 0)],
                i[(0, 1)],
                i[(0, 2)],
                i[(1, 1)],
                i[(1, 2)],
                i[(2, 2)],
            ],
            loss: loss.into(),
            loss_scale,
        }
    }
}

impl TryFrom<&pb::Constraint> for Constraint {
    type Error = ConversionError;

    /// Checks the version, both endpoints, the measurement, a symmetric information matrix of six finite
    /// entries, and a valid robust loss.
    fn try_from(c: &pb::Constraint) -> Result<Self, ConversionError> {
        check_format_version(M, c.format_version)?;
        let kind = kind_from_pb(c.kind, M)?;
        let [xx, xy, xt, yy, yt, tt] =
            <[f64; 6]>::try_from(c.information.as_slice()).map_err(|_| {
                ConversionError::BadSize {
                    message: M,
                    field: "information",
                    expected: 6,
                    got: c.information.len(),
                }
            })?;
        for v in [xx, xy, xt, yy, yt, tt] {
            check_finite(v, M, "information")?;
        }
        let loss = loss_from_pb(c.loss, c.loss_scale, M)?;
        Ok(Self {
            kind,
            from: variable_from_pb(c.from.as_ref(), "from")?,
            to: variable_from_pb(c.to.as_ref(), "to")?,
            from_from_to: pose_from_pb(c.from_from_to.as_ref(), M, "from_from_to")?,
            information: Matrix3::new(xx, xy, xt, xy, yy, yt, xt, yt, tt),
            loss,
        })
    }
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;

    use super::*;

    fn sample() -> Constraint {
        Constraint {
            kind: ConstraintKind::NodeToSubmapInter,
            from: VariableId::Submap(SubmapId {
                trajectory: 2,
                index: 5,
            }),
            to: VariableId::Node(NodeId {
                trajectory: 1,
                index: 77,
            }),
            from_from_to: rigid2(1.5, -0.25, 0.3),
            information: Matrix3::new(400.0, 1.0, 2.0, 1.0, 300.0, 3.0, 2.0, 3.0, 1000.0),
            loss: RobustLoss::Huber { delta: 0.5 },
        }
    }

    #[test]
    fn constraints_round_trip() {
        let c = sample();
        let back = Constraint::try_from(&pb::Constraint::from(&c)).unwrap();
        assert_eq!(back.kind, c.kind);
        assert_eq!((back.from, back.to), (c.from, c.to));
        assert_eq!(back.information, c.information);
        assert_eq!(back.loss, c.loss);
        approx::assert_relative_eq!(back.from_from_to, c.from_from_to, epsilon = 1e-12);
        let losses = [
            RobustLoss::Trivial,
            RobustLoss::Cauchy { scale: 2.0 },
            RobustLoss::Dcs { phi: 1.0 },
            RobustLoss::TruncatedLeastSquares { threshold: 25.0 },
        ];
        for loss in losses {
            let c = Constraint { loss, ..sample() };
            assert_eq!(
                Constraint::try_from(&pb::Constraint::from(&c))
                    .unwrap()
                    .loss,
                loss
            );
        }
    }

    #[test]
    fn bad_constraints_are_refused() {
        let good = pb::Constraint::from(&sample());
        let mut missing = good.clone();
        missing.to = None;
        assert_eq!(
            Constraint::try_from(&missing).unwrap_err(),
            ConversionError::MissingField {
                message: "Constraint",
                field: "to"
            }
        );
        let mut short = good.clone();
        short.information.pop();
        assert!(matches!(
            Constraint::try_from(&short),
            Err(ConversionError::BadSize {
                field: "information",
                ..
            })
        ));
        let mut nan = good.clone();
        nan.information[3] = f64::NAN;
        assert!(matches!(
            Constraint::try_from(&nan),
            Err(ConversionError::NotFinite { .. })
        ));
        let mut loss = good;
        loss.loss_scale = -1.0;
        assert!(matches!(
            Constraint::try_from(&loss),
            Err(ConversionError::OutOfRange { .. })
        ));
    }
}

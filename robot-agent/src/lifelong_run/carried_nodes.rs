//! Where a trimmed node's scans end up in a run's final trajectory: carried with the map.
//!
//! A trimmed node leaves the graph at the pose it had then; the map goes on moving (later sessions close
//! loops through the trees that replaced it). Left at that pose, a relation between its scan and a scan
//! the map kept compares two moments of the map, not the map. So each trimmed node is tied, when it goes,
//! to the nearest node the map keeps (`anchor_from_node` at that moment), and the final trajectory places
//! it where its anchor ends up: the pose the map's final estimate of that place implies.

use std::collections::BTreeMap;

use mapping::geometry::Rigid2;
use mapping::pose_graph::NodeId;

/// A removed node tied to the node the map kept nearest to it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct CarriedNode {
    /// The removed node.
    pub node: NodeId,
    /// The kept node nearest to it (translation) when it was removed.
    pub anchor: NodeId,
    /// `anchor⁻¹ · node` at that moment.
    pub anchor_from_node: Rigid2,
}

/// Ties each of `removed` (nodes and their poses as they went) to the nearest of `kept` (the nodes the map
/// holds after the removal, at their poses then). None when nothing is kept.
pub(super) fn carry(removed: &[(NodeId, Rigid2)], kept: &[(NodeId, Rigid2)]) -> Vec<CarriedNode> {
    removed
        .iter()
        .filter_map(|&(node, pose)| {
            let (anchor, anchor_pose) = kept.iter().min_by(|(_, a), (_, b)| {
                let da = (a.translation.vector - pose.translation.vector).norm_squared();
                let db = (b.translation.vector - pose.translation.vector).norm_squared();
                da.total_cmp(&db)
            })?;
            Some(CarriedNode {
                node,
                anchor: *anchor,
                anchor_from_node: anchor_pose.inverse() * pose,
            })
        })
        .collect()
}

/// Places each node of `carried` (in the order they were removed) where its anchor is in `poses`, an
/// anchor removed later first: an anchor is a node kept when its node went, so it is either still in the
/// map or removed after it.
pub(super) fn place_carried(poses: &mut BTreeMap<NodeId, Rigid2>, carried: &[CarriedNode]) {
    for c in carried.iter().rev() {
        if let Some(anchor) = poses.get(&c.anchor).copied() {
            poses.insert(c.node, anchor * c.anchor_from_node);
        }
    }
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;

    use super::*;

    fn n(index: u32) -> NodeId {
        NodeId {
            trajectory: 0,
            index,
        }
    }

    #[test]
    fn a_removed_node_follows_the_nearest_kept_node() {
        let kept = [
            (n(1), rigid2(0.0, 0.0, 0.0)),
            (n(2), rigid2(10.0, 0.0, 0.0)),
        ];
        let carried = carry(&[(n(3), rigid2(9.0, 1.0, 0.5))], &kept);
        assert_eq!(carried.len(), 1);
        assert_eq!(carried[0].anchor, n(2));
        // The map later moves node 2 by a turn and a shift: node 3 moves with it, rigidly.
        let moved = rigid2(1.0, 2.0, 0.3);
        let mut poses = BTreeMap::from([(n(1), rigid2(0.0, 0.0, 0.0)), (n(2), moved * kept[1].1)]);
        place_carried(&mut poses, &carried);
        let expected = moved * rigid2(9.0, 1.0, 0.5);
        assert!((poses[&n(3)].translation.vector - expected.translation.vector).norm() < 1e-12);
        assert!((poses[&n(3)].rotation.angle() - expected.rotation.angle()).abs() < 1e-12);
    }

    #[test]
    fn a_chain_of_removals_resolves_from_the_last_removed() {
        // Node 3 went first, anchored to node 2; node 2 went later, anchored to node 1.
        let first = carry(
            &[(n(3), rigid2(2.0, 0.0, 0.0))],
            &[(n(1), rigid2(0.0, 0.0, 0.0)), (n(2), rigid2(1.5, 0.0, 0.0))],
        );
        let second = carry(
            &[(n(2), rigid2(1.5, 0.0, 0.0))],
            &[(n(1), rigid2(0.0, 0.0, 0.0))],
        );
        let carried: Vec<_> = first.into_iter().chain(second).collect();
        let mut poses = BTreeMap::from([(n(1), rigid2(0.0, 5.0, 0.0))]);
        place_carried(&mut poses, &carried);
        assert!(
            (poses[&n(2)].translation.vector - rigid2(1.5, 5.0, 0.0).translation.vector).norm()
                < 1e-12
        );
        assert!(
            (poses[&n(3)].translation.vector - rigid2(2.0, 5.0, 0.0).translation.vector).norm()
                < 1e-12
        );
    }

    #[test]
    fn nothing_kept_carries_nothing() {
        assert!(carry(&[(n(3), rigid2(0.0, 0.0, 0.0))], &[]).is_empty());
    }
}

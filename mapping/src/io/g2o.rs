//! Reader and writer for 2D pose graphs in g2o and TORO text formats.
//!
//! g2o: `VERTEX_SE2 id x y θ`, `EDGE_SE2 i j dx dy dθ I11 I12 I13 I22 I23 I33`, `FIX id`.
//! TORO: `VERTEX2 id x y θ`, `EDGE2 i j dx dy dθ I11 I12 I22 I33 I13 I23` (another order of the
//! information entries). Both may appear in one file; `#` starts a comment line.
//!
//! File ids become `NodeId { trajectory: 0, index: id }`; edges become [`ConstraintKind::Odometry`] when
//! `j = i + 1` and [`ConstraintKind::NodeToNode`] otherwise, with a trivial loss. Nodes without a vertex
//! line (e.g. edges-only files such as CSAIL.g2o) get initial values by composing the odometry chain
//! (`j = i + 1` edges, forwards then backwards) from the nodes that have one, then by breadth-first search
//! over any edge; a component with no known pose at all is anchored at its smallest id, at the origin.

use std::collections::{BTreeMap, VecDeque};
use std::io::{BufRead, Write};

use nalgebra::Matrix3;
use thiserror::Error;

use crate::geometry::{Rigid2, Rigid2Ext as _, rigid2};
use crate::pose_graph::{
    Constraint, ConstraintKind, NodeId, PoseGraph, PoseGraphError, RobustLoss, VariableId,
};

/// Errors from reading or writing g2o/TORO files.
#[derive(Debug, Error)]
pub enum G2oError {
    /// Reading failed.
    #[error("line {line}: read error: {source}")]
    Read {
        /// 1-based line number.
        line: usize,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A line could not be parsed.
    #[error("line {line}: {message}")]
    Parse {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// The graph rejected a vertex or edge (duplicate vertex, self-loop, invalid information…).
    #[error("line {line}: {source}")]
    Graph {
        /// 1-based line number.
        line: usize,
        /// The graph's error.
        source: PoseGraphError,
    },
    /// The file holds no vertex and no edge.
    #[error("no vertices or edges found")]
    Empty,
    /// The writer can only store trajectory-0 nodes (g2o has one integer id space).
    #[error("variable {0:?} has no g2o id (only trajectory-0 nodes can be written)")]
    NotRepresentable(VariableId),
    /// Writing failed.
    #[error("write error: {0}")]
    Write(#[from] std::io::Error),
}

/// Which vertex/edge tags a file used.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GraphFormat {
    /// Only `VERTEX_SE2`/`EDGE_SE2`.
    G2o,
    /// Only `VERTEX2`/`EDGE2`.
    Toro,
    /// Both.
    Mixed,
}

/// A parsed pose-graph file.
#[derive(Clone, Debug)]
pub struct ParsedGraph {
    /// The graph; nodes without vertex lines are initialised as described in the module docs.
    pub graph: PoseGraph,
    /// Which tags the file used.
    pub format: GraphFormat,
    /// Number of vertex lines.
    pub vertex_lines: usize,
    /// Number of edge lines.
    pub edge_lines: usize,
    /// Number of nodes whose initial pose was computed from edges.
    pub initialized_from_edges: usize,
}

struct Edge {
    line: usize,
    from: u32,
    to: u32,
    from_from_to: Rigid2,
    information: Matrix3<f64>,
}

fn node(index: u32) -> VariableId {
    VariableId::Node(NodeId {
        trajectory: 0,
        index,
    })
}

fn parse_fields<'a>(
    line: usize,
    tag: &str,
    fields: impl Iterator<Item = &'a str>,
    expected: usize,
) -> Result<Vec<f64>, G2oError> {
    let fields: Vec<&str> = fields.collect();
    if fields.len() != expected {
        return Err(G2oError::Parse {
            line,
            message: format!(
                "{tag} needs {expected} fields after the tag, found {}",
                fields.len()
            ),
        });
    }
    fields
        .iter()
        .map(|f| {
            f.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| G2oError::Parse {
                    line,
                    message: format!("{tag}: {f:?} is not a finite number"),
                })
        })
        .collect()
}

fn parse_id(line: usize, value: f64) -> Result<u32, G2oError> {
    if value >= 0.0 && value <= f64::from(u32::MAX) && value.fract() == 0.0 {
        Ok(value as u32)
    } else {
        Err(G2oError::Parse {
            line,
            message: format!("{value} is not a valid vertex id"),
        })
    }
}

/// Reads a g2o or TORO 2D pose graph (formats detected per line).
pub fn read_pose_graph(reader: impl BufRead) -> Result<ParsedGraph, G2oError> {
    let mut vertices: BTreeMap<u32, (usize, Rigid2)> = BTreeMap::new();
    let mut edges: Vec<Edge> = Vec::new();
    let mut fixed: Vec<(usize, u32)> = Vec::new();
    let (mut saw_g2o, mut saw_toro) = (false, false);
    for (k, text) in reader.lines().enumerate() {
        let line = k + 1;
        let text = text.map_err(|source| G2oError::Read { line, source })?;
        let mut tokens = text.split_whitespace();
        let Some(tag) = tokens.next() else { continue };
        if tag.starts_with('#') {
            continue;
        }
        match tag {
            "VERTEX_SE2" | "VERTEX2" => {
                saw_g2o |= tag == "VERTEX_SE2";
                saw_toro |= tag == "VERTEX2";
                let v = parse_fields(line, tag, tokens, 4)?;
                let id = parse_id(line, v[0])?;
                if vertices
                    .insert(id, (line, rigid2(v[1], v[2], v[3])))
                    .is_some()
                {
                    return Err(G2oError::Graph {
                        line,
                        source: PoseGraphError::DuplicateVariable(node(id)),
                    });
                }
            }
            "EDGE_SE2" | "EDGE2" => {
                let toro = tag == "EDGE2";
                saw_g2o |= !toro;
                saw_toro |= toro;
                let v = parse_fields(line, tag, tokens, 11)?;
                let (from, to) = (parse_id(line, v[0])?, parse_id(line, v[1])?);
                // Upper-triangle entries (i11, i12, i13, i22, i23, i33) in each format's order.
                let [i11, i12, i13, i22, i23, i33] = if toro {
                    [v[5], v[6], v[9], v[7], v[10], v[8]]
                } else {
                    [v[5], v[6], v[7], v[8], v[9], v[10]]
                };
                let information = Matrix3::new(i11, i12, i13, i12, i22, i23, i13, i23, i33);
                edges.push(Edge {
                    line,
                    from,
                    to,
                    from_from_to: rigid2(v[2], v[3], v[4]),
                    information,
                });
            }
            "FIX" => {
                let v = parse_fields(line, tag, tokens, 1)?;
                fixed.push((line, parse_id(line, v[0])?));
            }
            other => {
                return Err(G2oError::Parse {
                    line,
                    message: format!("unknown tag {other:?}"),
                });
            }
        }
    }
    if vertices.is_empty() && edges.is_empty() {
        return Err(G2oError::Empty);
    }
    let vertex_lines = vertices.len();
    let mut poses: BTreeMap<u32, Rigid2> = vertices
        .iter()
        .map(|(id, (_, pose))| (*id, *pose))
        .collect();
    let before = poses.len();
    initialize_missing(&mut poses, &edges);
    let initialized_from_edges = poses.len() - before;
    // Finite edges can still compose to infinite poses (translations near f64::MAX).
    if let Some((id, _)) = poses.iter().find(|(_, pose)| {
        !(pose.x().is_finite() && pose.y().is_finite() && pose.theta().is_finite())
    }) {
        let line = vertices.get(id).map_or(0, |(line, _)| *line);
        return Err(G2oError::Parse {
            line,
            message: format!(
                "the initial pose of vertex {id}, composed from the edges, is not finite"
            ),
        });
    }

    let mut graph = PoseGraph::new();
    for (&id, pose) in &poses {
        let line = vertices.get(&id).map_or(0, |(line, _)| *line);
        graph
            .add_variable(node(id), *pose)
            .map_err(|source| G2oError::Graph { line, source })?;
    }
    for edge in &edges {
        let kind = if edge.to == edge.from.wrapping_add(1) {
            ConstraintKind::Odometry
        } else {
            ConstraintKind::NodeToNode
        };
        graph
            .add_constraint(Constraint {
                kind,
                from: node(edge.from),
                to: node(edge.to),
                from_from_to: edge.from_from_to,
                information: edge.information,
                loss: RobustLoss::Trivial,
            })
            .map_err(|source| G2oError::Graph {
                line: edge.line,
                source,
            })?;
    }
    for (line, id) in fixed {
        graph
            .set_fixed(node(id), true)
            .map_err(|source| G2oError::Graph { line, source })?;
    }
    let format = match (saw_g2o, saw_toro) {
        (true, true) => GraphFormat::Mixed,
        (false, true) => GraphFormat::Toro,
        _ => GraphFormat::G2o,
    };
    Ok(ParsedGraph {
        graph,
        format,
        vertex_lines,
        edge_lines: edges.len(),
        initialized_from_edges,
    })
}

/// Gives every node mentioned by an edge a pose: odometry chain first, then BFS over all edges.
fn initialize_missing(poses: &mut BTreeMap<u32, Rigid2>, edges: &[Edge]) {
    let mut needed: Vec<u32> = edges
        .iter()
        .flat_map(|e| [e.from, e.to])
        .filter(|id| !poses.contains_key(id))
        .collect();
    needed.sort_unstable();
    needed.dedup();
    if needed.is_empty() {
        return;
    }
    // First odometry edge per consecutive pair, in ascending order of `from`.
    let mut odometry: BTreeMap<u32, Rigid2> = BTreeMap::new();
    for e in edges.iter().filter(|e| e.to == e.from.wrapping_add(1)) {
        odometry.entry(e.from).or_insert(e.from_from_to);
    }
    let mut adjacency: BTreeMap<u32, Vec<(u32, Rigid2)>> = BTreeMap::new();
    for e in edges {
        adjacency
            .entry(e.from)
            .or_default()
            .push((e.to, e.from_from_to));
        adjacency
            .entry(e.to)
            .or_default()
            .push((e.from, e.from_from_to.inverse()));
    }
    for (&i, z) in &odometry {
        let next = i.wrapping_add(1);
        if let (Some(&xi), false) = (poses.get(&i), poses.contains_key(&next)) {
            poses.insert(next, xi * z);
        }
    }
    for (&i, z) in odometry.iter().rev() {
        if let (Some(&xj), false) = (poses.get(&i.wrapping_add(1)), poses.contains_key(&i)) {
            poses.insert(i, xj * z.inverse());
        }
    }
    let known: Vec<u32> = poses.keys().copied().collect();
    grow(poses, &adjacency, known);
    // Each component still without a pose is anchored at its smallest id, at the origin, and grown the same
    // way from that node only (odometry chain forwards, then any edge): a file of many small components
    // costs O(nodes + edges), not O(components × edges).
    for &seed in &needed {
        if poses.contains_key(&seed) {
            continue;
        }
        poses.insert(seed, Rigid2::identity());
        let mut added = vec![seed];
        let mut i = seed;
        while let (Some(z), Some(&xi)) = (odometry.get(&i), poses.get(&i)) {
            let next = i.wrapping_add(1);
            if poses.contains_key(&next) {
                break;
            }
            poses.insert(next, xi * z);
            added.push(next);
            i = next;
        }
        grow(poses, &adjacency, added);
    }
}

/// Breadth-first search from `start` over any edge, posing every node it reaches that has no pose yet.
fn grow(
    poses: &mut BTreeMap<u32, Rigid2>,
    adjacency: &BTreeMap<u32, Vec<(u32, Rigid2)>>,
    start: Vec<u32>,
) {
    let mut queue: VecDeque<u32> = start.into();
    while let Some(i) = queue.pop_front() {
        let Some(&xi) = poses.get(&i) else { continue };
        for &(j, z) in adjacency.get(&i).map_or(&[][..], Vec::as_slice) {
            if let std::collections::btree_map::Entry::Vacant(slot) = poses.entry(j) {
                slot.insert(xi * z);
                queue.push_back(j);
            }
        }
    }
}

/// Writes `graph` as g2o (`VERTEX_SE2`, `EDGE_SE2`, `FIX`), with round-trip-exact numbers.
///
/// Only trajectory-0 nodes can be written (their index becomes the g2o id).
pub fn write_pose_graph(graph: &PoseGraph, mut writer: impl Write) -> Result<(), G2oError> {
    let file_id = |id: VariableId| match id {
        VariableId::Node(NodeId {
            trajectory: 0,
            index,
        }) => Ok(index),
        other => Err(G2oError::NotRepresentable(other)),
    };
    for (id, pose, _) in graph.variables() {
        writeln!(
            writer,
            "VERTEX_SE2 {} {} {} {}",
            file_id(id)?,
            pose.x(),
            pose.y(),
            pose.theta()
        )?;
    }
    for (_, c) in graph.constraints() {
        let z = &c.from_from_to;
        let i = &c.information;
        writeln!(
            writer,
            "EDGE_SE2 {} {} {} {} {} {} {} {} {} {} {}",
            file_id(c.from)?,
            file_id(c.to)?,
            z.x(),
            z.y(),
            z.theta(),
            i[(0, 0)],
            i[(0, 1)],
            i[(0, 2)],
            i[(1, 1)],
            i[(1, 2)],
            i[(2, 2)]
        )?;
    }
    for (id, _, fixed) in graph.variables() {
        if fixed {
            writeln!(writer, "FIX {}", file_id(id)?)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::fmt::Write as _;

    use approx::assert_relative_eq;

    use super::*;

    fn read(text: &str) -> Result<ParsedGraph, G2oError> {
        read_pose_graph(text.as_bytes())
    }

    fn pose(graph: &PoseGraph, index: u32) -> Rigid2 {
        graph.pose(node(index)).unwrap()
    }

    const EDGE_TAIL: &str = "0 0 1 0 0 1 0 1";

    /// Fuzz finding (regression): an odometry edge from id 4294967295 to 0 (`j = i + 1` wrapping)
    /// overflowed `i + 1` while initialising the chain.
    #[test]
    fn an_odometry_edge_from_the_largest_id_initializes() {
        let parsed = read(&format!("EDGE_SE2 4294967295 0 1 {EDGE_TAIL}\n")).unwrap();
        assert_eq!(parsed.graph.num_variables(), 2);
        // Anchored at its smallest id, 0; the edge says 0 is 1 m ahead of 4294967295.
        assert_relative_eq!(pose(&parsed.graph, 0).x(), 0.0);
        assert_relative_eq!(pose(&parsed.graph, u32::MAX).x(), -1.0);
    }

    /// Fuzz finding (regression): finite edges composed into infinite initial poses.
    #[test]
    fn initial_poses_that_overflow_are_refused() {
        let text = format!(
            "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1e308 {EDGE_TAIL}\nEDGE_SE2 1 2 1e308 {EDGE_TAIL}\n"
        );
        let err = read(&text).unwrap_err().to_string();
        assert!(
            err.contains("vertex 2") && err.contains("not finite"),
            "{err}"
        );
    }

    /// Every component without a vertex is anchored at its smallest id, each grown from its own seed
    /// (many components once cost a breadth-first search over the whole graph each).
    #[test]
    fn components_without_vertices_are_anchored_one_by_one() {
        let mut text = String::new();
        for k in 0..2000_u32 {
            writeln!(text, "EDGE_SE2 {} {} 2 {EDGE_TAIL}", 3 * k, 3 * k + 2).unwrap();
        }
        let parsed = read(&text).unwrap();
        assert_eq!(parsed.initialized_from_edges, 4000);
        for k in [0, 1234, 1999] {
            assert_relative_eq!(pose(&parsed.graph, 3 * k).x(), 0.0);
            assert_relative_eq!(pose(&parsed.graph, 3 * k + 2).x(), 2.0);
        }
    }

    #[test]
    fn reads_g2o_vertices_edges_and_full_information() {
        let parsed = read(
            "# comment\n\
             VERTEX_SE2 0 0 0 0\n\
             VERTEX_SE2 1 1.5 -0.5 0.25\n\
             \n\
             EDGE_SE2 0 1 1.4 -0.4 0.2 1 2 3 4 5 6\n\
             FIX 0\n",
        )
        .unwrap();
        assert_eq!(parsed.format, GraphFormat::G2o);
        assert_eq!(
            (
                parsed.vertex_lines,
                parsed.edge_lines,
                parsed.initialized_from_edges
            ),
            (2, 1, 0)
        );
        let graph = &parsed.graph;
        assert_relative_eq!(pose(graph, 1), rigid2(1.5, -0.5, 0.25));
        assert_eq!(graph.is_fixed(node(0)), Some(true));
        let (_, c) = graph.constraints().next().unwrap();
        assert_eq!(c.kind, ConstraintKind::Odometry);
        assert_eq!(
            c.information,
            Matrix3::new(1.0, 2.0, 3.0, 2.0, 4.0, 5.0, 3.0, 5.0, 6.0)
        );
        assert_relative_eq!(c.from_from_to, rigid2(1.4, -0.4, 0.2));
    }

    #[test]
    fn reads_toro_information_order() {
        // TORO: I11 I12 I22 I33 I13 I23.
        let parsed =
            read("VERTEX2 3 0 0 0\nVERTEX2 7 1 0 0\nEDGE2 3 7 1 0 0 1 2 4 6 3 5\n").unwrap();
        assert_eq!(parsed.format, GraphFormat::Toro);
        let (_, c) = parsed.graph.constraints().next().unwrap();
        assert_eq!(c.kind, ConstraintKind::NodeToNode);
        assert_eq!(
            c.information,
            Matrix3::new(1.0, 2.0, 3.0, 2.0, 4.0, 5.0, 3.0, 5.0, 6.0)
        );
    }

    #[test]
    fn edges_only_files_are_initialized_by_the_odometry_chain_then_bfs() {
        let parsed = read(
            "EDGE_SE2 0 1 1 0 1.5707963267948966 1 0 0 1 0 1\n\
             EDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n\
             EDGE_SE2 0 2 5 5 0 1 0 0 1 0 1\n\
             EDGE_SE2 2 9 0 2 0 1 0 0 1 0 1\n",
        )
        .unwrap();
        assert_eq!(parsed.vertex_lines, 0);
        assert_eq!(parsed.initialized_from_edges, 4);
        let graph = &parsed.graph;
        assert_relative_eq!(pose(graph, 0), Rigid2::identity());
        assert_relative_eq!(
            pose(graph, 1),
            rigid2(1.0, 0.0, std::f64::consts::FRAC_PI_2),
            epsilon = 1e-12
        );
        // The chain (0→1→2), not the conflicting loop edge 0→2, places node 2.
        assert_relative_eq!(
            pose(graph, 2),
            rigid2(1.0, 1.0, std::f64::consts::FRAC_PI_2),
            epsilon = 1e-12
        );
        // Node 9 is off the chain: reached by BFS through 2→9.
        assert_relative_eq!(
            pose(graph, 9),
            rigid2(-1.0, 1.0, std::f64::consts::FRAC_PI_2),
            epsilon = 1e-12
        );
    }

    #[test]
    fn missing_vertices_chain_backwards_from_known_ones() {
        let parsed = read("VERTEX_SE2 1 10 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n").unwrap();
        assert_relative_eq!(
            pose(&parsed.graph, 0),
            rigid2(9.0, 0.0, 0.0),
            epsilon = 1e-12
        );
    }

    #[test]
    fn errors_carry_line_numbers() {
        let cases = [
            (
                "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0\n",
                2,
                "needs 4 fields",
            ),
            (
                "VERTEX_SE2 0 0 0 0\n\nEDGE_SE2 0 1 a 0 0 1 0 0 1 0 1\n",
                3,
                "not a finite number",
            ),
            ("VERTEX_SE2 -1 0 0 0\n", 1, "not a valid vertex id"),
            ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n", 1, "unknown tag"),
            (
                "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n",
                2,
                "already exists",
            ),
            (
                "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n",
                2,
                "to itself",
            ),
            (
                "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n",
                3,
                "information",
            ),
        ];
        assert!(cases.len() >= 3);
        for (text, line, needle) in cases {
            let message = read(text).unwrap_err().to_string();
            assert!(message.starts_with(&format!("line {line}:")), "{message}");
            assert!(message.contains(needle), "{message} lacks {needle:?}");
        }
        assert!(matches!(read("# nothing\n"), Err(G2oError::Empty)));
    }

    #[test]
    fn write_then_read_round_trips_exactly() {
        let text = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.0000000000000002 -3.3 2.9\nVERTEX_SE2 5 7 8 -1\n\
                    EDGE_SE2 0 1 1 0.1 0.3 10 0.5 0.25 20 0.125 30\nEDGE_SE2 1 5 2 2 2 1 0 0 1 0 1\nFIX 1\n";
        let graph = read(text).unwrap().graph;
        let mut out = Vec::new();
        write_pose_graph(&graph, &mut out).unwrap();
        let again = read_pose_graph(out.as_slice()).unwrap().graph;
        assert_eq!(
            graph.variables().collect::<Vec<_>>(),
            again.variables().collect::<Vec<_>>()
        );
        let edges = |g: &PoseGraph| g.constraints().map(|(_, c)| c.clone()).collect::<Vec<_>>();
        assert_eq!(edges(&graph), edges(&again));
    }

    #[test]
    fn writer_rejects_ids_it_cannot_express() {
        let mut graph = PoseGraph::new();
        let id = VariableId::Node(NodeId {
            trajectory: 1,
            index: 0,
        });
        graph.add_variable(id, Rigid2::identity()).unwrap();
        assert!(
            matches!(write_pose_graph(&graph, Vec::new()), Err(G2oError::NotRepresentable(v)) if v == id)
        );
    }

    #[test]
    fn reads_csail_edges_only_file() {
        let path = test_support::datasets_dir().join("posegraphs/CSAIL.g2o");
        let file = std::fs::File::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let parsed = read_pose_graph(std::io::BufReader::new(file)).unwrap();
        assert_eq!(
            (parsed.graph.num_variables(), parsed.graph.num_constraints()),
            (1045, 1172)
        );
        assert_eq!(parsed.initialized_from_edges, 1045);
        // Odometry edges are satisfied exactly by the chain initialisation.
        for (_, c) in parsed
            .graph
            .constraints()
            .filter(|(_, c)| c.kind == ConstraintKind::Odometry)
            .take(50)
        {
            let chi2 = c.chi2(
                &parsed.graph.pose(c.from).unwrap(),
                &parsed.graph.pose(c.to).unwrap(),
            );
            assert!(chi2 < 1e-12, "{chi2}");
        }
    }
}

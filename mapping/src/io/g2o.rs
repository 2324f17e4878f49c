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
    loop {
        for (&i, z) in &odometry {
            if let (Some(&xi), false) = (poses.get(&i), poses.contains_key(&(i + 1))) {
                poses.insert(i + 1, xi * z);
            }
        }
        for (&i, z) in odometry.iter().rev() {
            if let (Some(&xj), false) = (poses.get(&(i + 1)), poses.contains_key(&i)) {
                poses.insert(i, xj * z.inverse());
            }
        }
        let mut queue: VecDeque<u32> = poses.keys().copied().collect();
        while let Some(i) = queue.pop_front() {
            let Some(&xi) = poses.get(&i) else { continue };
            for &(j, z) in adjacency.get(&i).map_or(&[][..], Vec::as_slice) {
                if let std::collections::btree_map::Entry::Vacant(slot) = poses.entry(j) {
                    slot.insert(xi * z);
                    queue.push_back(j);
                }
            }
        }
        match needed.iter().find(|id| !poses.contains_key(id)) {
            Some(&seed) => {
                poses.insert(seed, Rigid2::identity());
            }
            None => return,
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

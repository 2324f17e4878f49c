//! The pose graph: variables (node and submap poses in the world frame) and constraints between them.
//!
//! Adding and removing variables and constraints is cheap (`O(log n + degree)`), so that a sparsifier can
//! edit the graph freely; iteration is deterministic (variables by id, constraints by insertion order).

use std::collections::BTreeMap;

use nalgebra::Matrix3;
use thiserror::Error;

use super::constraint::Constraint;
use super::ids::{ConstraintId, VariableId};
use crate::geometry::Rigid2;

/// Errors from editing a [`PoseGraph`].
#[derive(Debug, Error, Clone, PartialEq)]
pub enum PoseGraphError {
    /// The variable is already in the graph.
    #[error("variable {0:?} already exists")]
    DuplicateVariable(VariableId),
    /// The variable is not in the graph.
    #[error("unknown variable {0:?}")]
    UnknownVariable(VariableId),
    /// The constraint is not in the graph.
    #[error("unknown constraint {0:?}")]
    UnknownConstraint(ConstraintId),
    /// A constraint must join two different variables.
    #[error("constraint joins {0:?} to itself")]
    SelfLoop(VariableId),
    /// A pose, measurement or information matrix holds NaN or infinity.
    #[error("non-finite value in {0}")]
    NonFinite(&'static str),
    /// The information matrix is not symmetric or has a negative diagonal entry.
    #[error("information matrix is not symmetric with a non-negative diagonal")]
    InvalidInformation,
    /// The robust loss has a non-positive or non-finite parameter.
    #[error("invalid robust loss parameter")]
    InvalidLoss,
    /// A graph rebuilt from parts ([`PoseGraph::from_parts`]) repeats a constraint id, or its next id is
    /// not above every constraint's.
    #[error("constraint id {0:?} repeated or not below the next id")]
    ConstraintIdOutOfOrder(ConstraintId),
}

#[derive(Clone, Debug, PartialEq)]
struct Variable {
    pose: Rigid2,
    fixed: bool,
    /// Constraints touching this variable, sorted (ids increase with insertion).
    constraints: Vec<ConstraintId>,
}

/// A 2D pose graph.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PoseGraph {
    variables: BTreeMap<VariableId, Variable>,
    constraints: BTreeMap<ConstraintId, Constraint>,
    next_constraint: u64,
}

fn is_finite_pose(pose: &Rigid2) -> bool {
    pose.translation.vector.iter().all(|v| v.is_finite())
        && pose.rotation.re.is_finite()
        && pose.rotation.im.is_finite()
}

impl PoseGraph {
    /// An empty graph.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a free variable with its initial `world_from_variable` estimate.
    pub fn add_variable(&mut self, id: VariableId, initial: Rigid2) -> Result<(), PoseGraphError> {
        if !is_finite_pose(&initial) {
            return Err(PoseGraphError::NonFinite("initial pose"));
        }
        if self.variables.contains_key(&id) {
            return Err(PoseGraphError::DuplicateVariable(id));
        }
        self.variables.insert(
            id,
            Variable {
                pose: initial,
                fixed: false,
                constraints: Vec::new(),
            },
        );
        Ok(())
    }

    /// Removes a variable and every constraint touching it; returns those constraints in id order.
    pub fn remove_variable(
        &mut self,
        id: VariableId,
    ) -> Result<Vec<(ConstraintId, Constraint)>, PoseGraphError> {
        let variable = self
            .variables
            .remove(&id)
            .ok_or(PoseGraphError::UnknownVariable(id))?;
        let mut removed = Vec::with_capacity(variable.constraints.len());
        for constraint_id in variable.constraints {
            let Some(constraint) = self.constraints.remove(&constraint_id) else {
                continue;
            };
            let other = if constraint.from == id {
                constraint.to
            } else {
                constraint.from
            };
            if let Some(other) = self.variables.get_mut(&other)
                && let Ok(k) = other.constraints.binary_search(&constraint_id)
            {
                other.constraints.remove(k);
            }
            removed.push((constraint_id, constraint));
        }
        Ok(removed)
    }

    /// Marks a variable as fixed (held constant by the optimizer) or free.
    pub fn set_fixed(&mut self, id: VariableId, fixed: bool) -> Result<(), PoseGraphError> {
        self.variables
            .get_mut(&id)
            .ok_or(PoseGraphError::UnknownVariable(id))?
            .fixed = fixed;
        Ok(())
    }

    /// Whether the variable is fixed; `None` if unknown.
    pub fn is_fixed(&self, id: VariableId) -> Option<bool> {
        self.variables.get(&id).map(|v| v.fixed)
    }

    /// The current `world_from_variable` estimate.
    pub fn pose(&self, id: VariableId) -> Option<Rigid2> {
        self.variables.get(&id).map(|v| v.pose)
    }

    /// Overwrites the current estimate of a variable.
    pub fn set_pose(&mut self, id: VariableId, pose: Rigid2) -> Result<(), PoseGraphError> {
        if !is_finite_pose(&pose) {
            return Err(PoseGraphError::NonFinite("pose"));
        }
        self.variables
            .get_mut(&id)
            .ok_or(PoseGraphError::UnknownVariable(id))?
            .pose = pose;
        Ok(())
    }

    /// Whether the graph has this variable.
    pub fn contains_variable(&self, id: VariableId) -> bool {
        self.variables.contains_key(&id)
    }

    /// Adds a constraint between two existing, distinct variables.
    pub fn add_constraint(
        &mut self,
        constraint: Constraint,
    ) -> Result<ConstraintId, PoseGraphError> {
        if constraint.from == constraint.to {
            return Err(PoseGraphError::SelfLoop(constraint.from));
        }
        for id in [constraint.from, constraint.to] {
            if !self.variables.contains_key(&id) {
                return Err(PoseGraphError::UnknownVariable(id));
            }
        }
        if !is_finite_pose(&constraint.from_from_to) {
            return Err(PoseGraphError::NonFinite("measurement"));
        }
        validate_information(&constraint.information)?;
        if !constraint.loss.is_valid() {
            return Err(PoseGraphError::InvalidLoss);
        }
        let id = ConstraintId(self.next_constraint);
        self.next_constraint += 1;
        for end in [constraint.from, constraint.to] {
            if let Some(v) = self.variables.get_mut(&end) {
                v.constraints.push(id);
            }
        }
        self.constraints.insert(id, constraint);
        Ok(id)
    }

    /// Removes a constraint and returns it.
    pub fn remove_constraint(&mut self, id: ConstraintId) -> Result<Constraint, PoseGraphError> {
        let constraint = self
            .constraints
            .remove(&id)
            .ok_or(PoseGraphError::UnknownConstraint(id))?;
        for end in [constraint.from, constraint.to] {
            if let Some(v) = self.variables.get_mut(&end)
                && let Ok(k) = v.constraints.binary_search(&id)
            {
                v.constraints.remove(k);
            }
        }
        Ok(constraint)
    }

    /// Replaces a constraint's information matrix in place (its id and place in the graph stay).
    pub fn set_information(
        &mut self,
        id: ConstraintId,
        information: Matrix3<f64>,
    ) -> Result<(), PoseGraphError> {
        validate_information(&information)?;
        let constraint = self
            .constraints
            .get_mut(&id)
            .ok_or(PoseGraphError::UnknownConstraint(id))?;
        constraint.information = information;
        Ok(())
    }

    /// The constraint with this id.
    pub fn constraint(&self, id: ConstraintId) -> Option<&Constraint> {
        self.constraints.get(&id)
    }

    /// Variables in id order, with their current estimate and fixed flag.
    pub fn variables(&self) -> impl Iterator<Item = (VariableId, Rigid2, bool)> + '_ {
        self.variables.iter().map(|(id, v)| (*id, v.pose, v.fixed))
    }

    /// The largest translation (metres) and rotation (radians) between this graph's and `other`'s
    /// estimates of the variables both hold: how far re-optimizing, sparsifying or deleting moved the map.
    pub fn largest_shift(&self, other: &PoseGraph) -> (f64, f64) {
        let mut shift = (0.0f64, 0.0f64);
        for (id, pose, _) in self.variables() {
            if let Some(moved) = other.pose(id) {
                let d = pose.inverse() * moved;
                shift.0 = shift
                    .0
                    .max((moved.translation.vector - pose.translation.vector).norm());
                shift.1 = shift.1.max(d.rotation.angle().abs());
            }
        }
        shift
    }

    /// Constraints in id (insertion) order.
    pub fn constraints(&self) -> impl Iterator<Item = (ConstraintId, &Constraint)> + '_ {
        self.constraints.iter().map(|(id, c)| (*id, c))
    }

    /// Constraints added at or after `first` (ids increase with insertion), in id order.
    pub fn constraints_since(
        &self,
        first: ConstraintId,
    ) -> impl Iterator<Item = (ConstraintId, &Constraint)> + '_ {
        self.constraints.range(first..).map(|(id, c)| (*id, c))
    }

    /// The id the next added constraint will get: with [`Self::constraints_since`], what was added after
    /// this moment.
    pub fn next_constraint_id(&self) -> ConstraintId {
        ConstraintId(self.next_constraint)
    }

    /// A graph rebuilt from what [`Self::variables`], [`Self::constraints`] and
    /// [`Self::next_constraint_id`] returned (a checkpoint): the same variables, the same constraints
    /// under the same ids, and the same next id, so the rebuilt graph equals the original and behaves
    /// identically. Fails on what [`Self::add_variable`] and [`Self::add_constraint`] refuse, on a
    /// repeated constraint id, and on a `next_constraint` not above every id.
    pub fn from_parts(
        variables: impl IntoIterator<Item = (VariableId, Rigid2, bool)>,
        constraints: impl IntoIterator<Item = (ConstraintId, Constraint)>,
        next_constraint: ConstraintId,
    ) -> Result<Self, PoseGraphError> {
        let mut graph = Self::new();
        for (id, pose, fixed) in variables {
            graph.add_variable(id, pose)?;
            graph.set_fixed(id, fixed)?;
        }
        let mut constraints: Vec<(ConstraintId, Constraint)> = constraints.into_iter().collect();
        constraints.sort_by_key(|(id, _)| *id);
        for (id, constraint) in constraints {
            if id.0 < graph.next_constraint {
                return Err(PoseGraphError::ConstraintIdOutOfOrder(id));
            }
            graph.next_constraint = id.0;
            graph.add_constraint(constraint)?;
        }
        if next_constraint.0 < graph.next_constraint {
            return Err(PoseGraphError::ConstraintIdOutOfOrder(next_constraint));
        }
        graph.next_constraint = next_constraint.0;
        Ok(graph)
    }

    /// Ids of the constraints touching a variable, in id order (empty if the variable is unknown).
    pub fn constraints_of(&self, id: VariableId) -> &[ConstraintId] {
        self.variables
            .get(&id)
            .map_or(&[], |v| v.constraints.as_slice())
    }

    /// Number of variables.
    pub fn num_variables(&self) -> usize {
        self.variables.len()
    }

    /// Number of constraints.
    pub fn num_constraints(&self) -> usize {
        self.constraints.len()
    }

    /// A copy with the same variables (poses and fixed flags) and, for each constraint, what `map` makes of
    /// it (`None` leaves it out): to change losses or drop constraints, e.g. loop closures an optimization
    /// rejected. Fails only if `map` returns an invalid constraint.
    pub fn with_constraints(
        &self,
        mut map: impl FnMut(&Constraint) -> Option<Constraint>,
    ) -> Result<PoseGraph, PoseGraphError> {
        let mut out = PoseGraph::new();
        for (id, pose, fixed) in self.variables() {
            out.add_variable(id, pose)?;
            out.set_fixed(id, fixed)?;
        }
        for (_, constraint) in self.constraints() {
            if let Some(constraint) = map(constraint) {
                out.add_constraint(constraint)?;
            }
        }
        Ok(out)
    }

    /// χ² = Σ eᵀΩe over all constraints (g2o convention, robust losses ignored).
    pub fn chi2(&self) -> f64 {
        self.sum_over_constraints(Constraint::chi2)
    }

    /// Σ ρ(eᵀΩe): the objective the optimizer minimises (equals [`PoseGraph::chi2`] without robust losses).
    pub fn cost(&self) -> f64 {
        self.sum_over_constraints(Constraint::cost)
    }

    fn sum_over_constraints(&self, term: impl Fn(&Constraint, &Rigid2, &Rigid2) -> f64) -> f64 {
        self.constraints
            .values()
            .map(
                |c| match (self.variables.get(&c.from), self.variables.get(&c.to)) {
                    (Some(a), Some(b)) => term(c, &a.pose, &b.pose),
                    _ => 0.0,
                },
            )
            .sum()
    }
}

fn validate_information(information: &Matrix3<f64>) -> Result<(), PoseGraphError> {
    if !information.iter().all(|v| v.is_finite()) {
        return Err(PoseGraphError::NonFinite("information"));
    }
    let scale = information.amax().max(f64::MIN_POSITIVE);
    let asymmetric = (information - information.transpose()).amax() > 1e-9 * scale;
    if asymmetric || (0..3).any(|k| information[(k, k)] < 0.0) {
        return Err(PoseGraphError::InvalidInformation);
    }
    Ok(())
}

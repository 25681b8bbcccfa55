//! What one projection did: the report the simulation books and shows per step.

/// What one projection did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProjectionReport {
    /// Iterations taken (0 when the base step already satisfied every row).
    pub iterations: usize,
    /// Every active row is within tolerance.
    pub converged: bool,
    /// Largest scaled residual `|c_i| / scale_i` at the base step's state.
    pub initial_residual: f64,
    /// Largest scaled residual at the returned state (compare with the tolerance).
    pub final_residual: f64,
    /// D-norm of the total correction `|q - q~|_D`, sqrt(kg) m.
    pub correction: f64,
    /// Final slack values.
    pub s: f64,
    pub t: f64,
    /// Not converged: the best iterate (or the base state) was kept.
    pub fallback: bool,
    /// The impact bound limited the correction (conservation is then not exact).
    pub bound_hit: bool,
    /// Small solves that needed the least-squares fallback.
    pub least_squares_solves: usize,
    /// Step halvings taken in total.
    pub halvings: usize,
    /// Number of active rows.
    pub active_rows: usize,
    /// Total energy `H(x*, v*)` of the base step's state, J (measured by the first evaluation).
    pub base_energy: f64,
    /// Smallest volume ratio of the base step's state (measured by the first evaluation).
    pub base_min_j: f64,
    /// The velocity warm start was used (energy error above `warm_start_threshold`).
    pub warm_start: bool,
    /// The position metric was `W = M + h^2 diag(K_0)` (see [`Metric`](super::Metric)).
    pub stiffness_metric: bool,
    /// The position metric was the base integrator's factorised matrix (see [`SystemMetric`](super::SystemMetric)); then
    /// `stiffness_metric` is false.
    pub system_metric: bool,
    /// Restarts from the base state after an attempt inverted tets the base step had upright.
    pub restarts: usize,
    /// Vertices whose positions were frozen by those restarts (their velocities stay free).
    pub frozen_vertices: usize,
    /// Elastic evaluations (energy, or energy and gradient, over all tets), the first one included unless the
    /// base step handed it over ([`Projector::offer_base_gradient`](super::Projector::offer_base_gradient): backward Euler): an iteration evaluates
    /// its trial point, and a second one where the full step overshoots.
    pub evaluations: usize,
    /// Fraction of the step's energy gap `H_target - H(x*, v*)` (a deficit to restore or an excess to remove)
    /// that the projection closed: 1 unless the quality guard or convergence limited it (see
    /// [`ProjectionSettings::quality_margin`](super::ProjectionSettings::quality_margin)).
    pub restored: f64,
    /// Energy the projection left between the base step's energy and the target, J (`-(1 - restored) * gap`
    /// with `gap = H_target - H(x*, v*)`: negative for a deficit it did not restore, positive for an excess it
    /// did not remove): booked as the step's unresolved energy, a budget source of its own, so that
    /// `H = H_0 + budget_total` still holds.
    pub unresolved: f64,
    /// The step's energy gap `H_target - H(x*, v*)`, J: what the base step lost (positive) or gained (negative)
    /// against its target.
    pub gap: f64,
    /// Projections tried in this step (1, plus one per restored fraction tried and per metric switch).
    pub trials: usize,
    /// The diagonal stiffness metric stalled (the scaled residual did not halve in an iteration after the
    /// first) and the projection restarted from the base state in the mass metric (see [`Metric::Auto`](super::Metric::Auto)).
    pub metric_switched: bool,
    /// The body was translated onto the centre-of-mass target before iterating (the closest point of those rows
    /// alone; see [`Projector::project_with`](super::Projector::project_with)).
    pub translated: bool,
    /// Largest change of a tet's volume ratio against the base step (at the end of the step or one step
    /// ahead), as a fraction of the quality margin, at the returned state; 0 where the guard did not run.
    pub quality_excess: f64,
    /// The projection stood down on a step of resting contact: no iteration was run, the state is the base
    /// step's, and its residual was booked as contact work (the simulation's resting-contact rule,
    /// [`crate::simulation::Simulation::step`]). Never set by the projection itself.
    pub stood_down: bool,
}

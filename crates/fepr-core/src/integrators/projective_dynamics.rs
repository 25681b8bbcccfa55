//! Projective Dynamics (Bouaziz, Martin, Liu, Kavan, Pauly 2014) for tets, with the strain constraint of
//! every element (projection of F onto rotations, weight `w_e = 2 mu V_e`):
//!
//! ```text
//! minimise  1/(2 h^2) |x - y|_M^2 + sum_e w_e/2 |F_e(x) - R_e|^2 - sum_i m_i g . x_i,   y = x_n + h v_n
//! ```
//!
//! alternating a local step (`R_e` = rotation of the polar decomposition of `F_e`, parallel over tets) and a
//! global step: one constant m x m matrix `M/h^2 + sum_e w_e G_e G_e^T` (G_e: the shape-function gradients),
//! factorised once per run (again when the step size or [`Model::key`] changes: material, masses, pins), solved
//! for the x, y and z coordinates together. Pinned vertices are eliminated.
//! The energy this minimises is the ARAP energy `Psi = mu |F - R|^2` ([`crate::material::Arap`]); with FEPR,
//! the model's material must be that energy so that H is the PD energy (fepr-spec section 5).
//!
//! Obstacles ([`Integrator::set_obstacles`]) enter the step as projective contact constraints on the vertices
//! that the inertial prediction puts within reach of an obstacle (the step's active set): each pulls its vertex to the
//! nearest point of the contact layer from its current iterate with weight `CONTACT_WEIGHT_RATIO m_i / h^2`
//! ([`CONTACT_WEIGHT_RATIO`]), in the global matrix, so that the global solve carries the support to the
//! whole body within the step. The matrix with these weights is factorised again when the active set changes
//! (numerically only: the symbolic analysis is kept); the plain matrix stays the projection's metric. Why not
//! project the iterates out of the obstacles between global solves (no new factorisation): the plain global
//! solve then does not know the contact vertices are held, the rest of the body falls on through them, and a
//! dropped armadillo at dt = 1/60 ended with 2,052 inverted tets (against 98 with the push-out after the step).
//! Vertices that the iterations bring within an obstacle's reach join the active set, up to
//! `ACTIVE_SET_REFRESHES` times a step; any later ones are left to the push-out after the step.

use crate::exec::for_each_chunk_mut;
use std::time::Instant;

use crate::elasticity::shape_gradients;
use crate::error::{invalid, FeprError, Result};
use crate::integrators::{
    finish_positional_step, CoupledSolve, HandOver, Integrator, SharedMetric, StepReport,
};
use crate::material::Material;
use crate::math::{add, scale, Vec3};
use crate::math::{LowerPattern, SparseCholesky};
use crate::model::{Model, ModelKey, State};
use crate::projection::SystemMetric;
use crate::world::{ContactPotential, Obstacle};

/// A contact constraint's weight in units of its vertex's inertia term `m_i / h^2`. A tenth of backward Euler's
/// penalty stiffness ([`crate::world::STIFFNESS_RATIO`]): Projective Dynamics' fixed iteration count leaves a
/// stiffer support ringing (a damped block resting on a slab on the floor kept 1e-5 J of kinetic energy after
/// 5 s at 1e4, under 1e-6 at 1e3), and its resting steps take no impact substeps at this weight (the armadillo
/// drop: one impact step in 4 substeps, none at rest).
const CONTACT_WEIGHT_RATIO: f64 = 1e3;

/// How often a step may add the vertices its iterations brought into an obstacle's reach to the contact active set.
const ACTIVE_SET_REFRESHES: usize = 2;
/// The same for a step taken together with other bodies, whose corrections may push vertices towards an obstacle
/// at any iteration.
const TOGETHER_REFRESHES: usize = 2;
use std::sync::{Arc, Mutex};

/// Projective Dynamics settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PdSettings {
    /// Local/global iterations per step (default 10).
    pub iterations: usize,
    /// Optional early stop: relative change of positions below this (default None: fixed count).
    pub tolerance: Option<f64>,
}

impl Default for PdSettings {
    fn default() -> Self {
        Self {
            iterations: 10,
            tolerance: None,
        }
    }
}

/// The global matrix and the scratch of its solves as a [`SystemMetric`]: shared by the integrator and the
/// hand-over, locked by whichever of them solves with it.
#[derive(Default)]
struct PdMatrix {
    pre: Option<Prefactored>,
    /// Right-hand sides, then solutions, of [`SystemMetric::solve`]: one row per free vertex.
    rhs: Vec<Vec3>,
}

struct Prefactored {
    free_vertices: Vec<usize>,
    chol: SparseCholesky,
    /// Coupling of free rows to pinned vertices: (free row, pinned vertex, coefficient).
    pinned_coupling: Vec<(usize, usize, f64)>,
    /// Shear modulus of the ARAP energy, Pa (the weights are `w_e = 2 mu V_e`).
    mu: f64,
    /// The step size the matrix `M / h^2 + L` was factorised for, s.
    h: f64,
    /// The [`Model::key`] it was factorised for.
    key: ModelKey,
    /// The matrix's pattern and values, and the value position of each free vertex's diagonal entry (for the
    /// matrix with contact weights).
    pattern: LowerPattern,
    values: Vec<f64>,
    diagonal: Vec<usize>,
    /// The matrix with the contact weights of an active set, factorised, with that set (sorted vertices).
    contact: Option<(SparseCholesky, Vec<usize>)>,
}

/// Wall-clock time of the phases of the last step, s (for benchmarks and profiling).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PdTiming {
    /// Local steps (polar decompositions), summed over the iterations.
    pub local: f64,
    /// Right-hand side assembly.
    pub rhs: f64,
    /// Triangular solves with the prefactored matrix.
    pub solve: f64,
}

/// Projective Dynamics integrator (prefactored global matrix, 3 right-hand sides per solve).
#[derive(Default)]
pub struct ProjectiveDynamics {
    pub settings: PdSettings,
    /// Phase times of the last step.
    pub timing: PdTiming,
    /// The factorised global matrix, shared with the hand-over as the projection's position metric.
    matrix: Arc<Mutex<PdMatrix>>,
    /// Symbolic analyses and numeric factorisations performed (one each per run, step size and model key).
    pub factorizations: usize,
    /// Per tet in the model's block order, the right-hand side terms `w_e R_e g_k` on its 4 corners (from the
    /// local step).
    corner_terms: Vec<[Vec3; 4]>,
    /// Global-step right-hand sides, then solutions: one row (x, y, z) per free vertex.
    rhs: Vec<Vec3>,
    /// `b - A x` of the plain global matrix at the iterate, one row per free vertex (the contact targets' Jacobi
    /// step).
    residual: Vec<Vec3>,
    x_n: Vec<Vec3>,
    x: Vec<Vec3>,
    y: Vec<Vec3>,
    /// The obstacles, as contact constraints (empty: none).
    contact: ContactPotential,
    /// The step's contact active set (sorted free vertices), and their constraints' targets in the last
    /// iteration, m.
    active: Vec<usize>,
    targets: Vec<Vec3>,
    target_vertices: Vec<usize>,
    /// The step in progress: its size (s), report, active-set refreshes so far, and whether it failed.
    step_h: f64,
    report: StepReport,
    refreshes: usize,
    failed: bool,
    /// Whether the step is taken together with other bodies ([`CoupledSolve`]), and whether the last
    /// iteration added vertices to the contact active set.
    together: bool,
    set_grew: bool,
}

impl std::fmt::Debug for ProjectiveDynamics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ProjectiveDynamics")
            .field("settings", &self.settings)
            .finish()
    }
}

/// `out = b - A x` for the free rows of the plain global matrix `A` (its lower triangle in `pre`, symmetric),
/// with `b` one row per free vertex and `x` the positions of every vertex (m).
fn residual_rows(pre: &Prefactored, x: &[Vec3], b: &[Vec3], out: &mut Vec<Vec3>) {
    out.clear();
    out.extend_from_slice(b);
    let p = &pre.pattern;
    for c in 0..p.n {
        let xc = x[pre.free_vertices[c]];
        for k in p.col_ptr[c]..p.col_ptr[c + 1] {
            let (r, a) = (p.row_idx[k], pre.values[k]);
            let xr = x[pre.free_vertices[r]];
            for d in 0..3 {
                out[r][d] -= a * xc[d];
            }
            if r != c {
                for d in 0..3 {
                    out[c][d] -= a * xr[d];
                }
            }
        }
    }
}

impl ProjectiveDynamics {
    pub fn new(settings: PdSettings) -> Result<Self> {
        if settings.iterations == 0 || settings.iterations > 10_000 {
            return Err(invalid(
                "pd_iterations",
                format!("must be in 1..=10000, got {}", settings.iterations),
            ));
        }
        if let Some(t) = settings.tolerance {
            if !(t.is_finite() && t > 0.0) {
                return Err(invalid(
                    "pd_tolerance",
                    format!("must be positive, got {t}"),
                ));
            }
        }
        Ok(Self {
            settings,
            ..Default::default()
        })
    }

    /// Factorises the global matrix with the contact weights of `active` (sorted free vertices) into
    /// `pre.contact`, reusing the symbolic analysis of an earlier active set (only the diagonal changes).
    /// Adds to `active` (sorted free vertices) those of `x` within an obstacle's reach, and factorises the matrix
    /// with the contact weights of the set when it differs from the one factorised last (which may be the last
    /// step's). Returns whether it factorised.
    fn extend_active_set(
        contact: &ContactPotential,
        active: &mut Vec<usize>,
        pre: &mut Prefactored,
        model: &Model,
        x: &[Vec3],
        inv_h2: f64,
    ) -> Result<bool> {
        let before = active.len();
        for i in 0..model.num_vertices() {
            if !model.pinned[i]
                && active[..before].binary_search(&i).is_err()
                && contact.in_reach(model, x[i])
            {
                active.push(i);
            }
        }
        active.sort_unstable();
        if active.is_empty() || pre.contact.as_ref().is_some_and(|c| c.1 == *active) {
            return Ok(false);
        }
        Self::factorize_contact(pre, model, active, inv_h2)?;
        Ok(true)
    }

    fn factorize_contact(
        pre: &mut Prefactored,
        model: &Model,
        active: &[usize],
        inv_h2: f64,
    ) -> Result<()> {
        let mut values = pre.values.clone();
        for &v in active {
            let c = pre.free_vertices.partition_point(|&f| f < v);
            values[pre.diagonal[c]] += CONTACT_WEIGHT_RATIO * model.masses[v] * inv_h2;
        }
        let mut chol = match pre.contact.take() {
            Some((chol, _)) => chol,
            None => SparseCholesky::analyse(&pre.pattern, 3)?,
        };
        chol.factorize(&values)?;
        pre.contact = Some((chol, active.to_vec()));
        Ok(())
    }

    fn prefactor(model: &Model, h: f64) -> Result<Prefactored> {
        let mu = match model.material {
            Material::Arap(a) => a.mu,
            _ => {
                return Err(FeprError::Simulation(
                    "projective_dynamics needs the PD (ARAP) material so that FEPR conserves the energy the solver \
                     minimises"
                        .into(),
                ))
            }
        };
        let m = model.num_vertices();
        let mut free_index = vec![usize::MAX; m];
        let mut free_vertices = Vec::new();
        for i in 0..m {
            if !model.pinned[i] {
                free_index[i] = free_vertices.len();
                free_vertices.push(i);
            }
        }
        let n = free_vertices.len();
        let grads: Vec<[Vec3; 4]> = (0..model.num_tets())
            .map(|e| shape_gradients(model, e))
            .collect();
        let weights: Vec<f64> = model.rest_volume.iter().map(|v| 2.0 * mu * v).collect();
        let mut columns = vec![Vec::new(); n];
        for t in model.mesh.tets() {
            for &p in t {
                for &q in t {
                    let (r, c) = (free_index[p], free_index[q]);
                    if r != usize::MAX && c != usize::MAX && r >= c {
                        columns[c].push(r);
                    }
                }
            }
        }
        let pattern = LowerPattern::from_columns(n, columns);
        let mut values = vec![0.0; pattern.nnz()];
        let mut pinned_coupling = Vec::new();
        let inv_h2 = 1.0 / (h * h);
        for (c, &v) in free_vertices.iter().enumerate() {
            values[pattern.position(c, c).expect("diagonal")] += model.masses[v] * inv_h2;
        }
        for (e, t) in model.mesh.tets().iter().enumerate() {
            let g = &grads[e];
            for a in 0..4 {
                for b in 0..4 {
                    let coef =
                        weights[e] * (g[a][0] * g[b][0] + g[a][1] * g[b][1] + g[a][2] * g[b][2]);
                    let (r, c) = (free_index[t[a]], free_index[t[b]]);
                    match (r != usize::MAX, c != usize::MAX) {
                        (true, true) if r >= c => {
                            values[pattern.position(r, c).expect("entry")] += coef
                        }
                        (true, false) => pinned_coupling.push((r, t[b], coef)),
                        _ => {}
                    }
                }
            }
        }
        let mut chol = SparseCholesky::analyse(&pattern, 3)?;
        chol.factorize(&values)?;
        let diagonal = (0..n)
            .map(|c| pattern.position(c, c).expect("diagonal"))
            .collect();
        Ok(Prefactored {
            free_vertices,
            chol,
            pinned_coupling,
            mu,
            h,
            key: model.key(),
            pattern,
            values,
            diagonal,
            contact: None,
        })
    }
}

/// The PD matrix as the projection's position metric: `W = h^2 A = M + h^2 L` (`A = M / h^2 + L`, the matrix
/// the global step solves with; `L = sum_e w_e G_e G_e^T`, per coordinate), factorised already. After a PD step
/// the projection's energy correction then moves the positions as a global step would (smooth modes first),
/// where the diagonal stiffness metric moved each vertex on its own.
impl SystemMetric for PdMatrix {
    fn solve(&mut self, model: &Model, h: f64, rhs: &[Vec3], out: &mut [Vec3]) -> bool {
        let Some(pre) = self.pre.as_mut() else {
            return false;
        };
        if pre.h != h || pre.key != model.key() {
            return false;
        }
        let inv_h2 = 1.0 / (h * h);
        let b = &mut self.rhs;
        b.clear();
        b.extend(pre.free_vertices.iter().map(|&v| scale(rhs[v], inv_h2)));
        pre.chol.solve3_in_place(b);
        out.iter_mut().for_each(|o| *o = [0.0; 3]);
        for (c, &v) in pre.free_vertices.iter().enumerate() {
            out[v] = b[c];
        }
        true
    }

    fn norm_sq(&self, model: &Model, h: f64, dx: &[Vec3]) -> f64 {
        // dx^T M dx + h^2 sum_e w_e |sum_k dx_k g_k^T|_F^2 (the tet's change of F), in tet order.
        let mu = match model.material {
            Material::Arap(a) => a.mu,
            _ => return f64::NAN,
        };
        let mass: f64 = (0..dx.len())
            .filter(|&i| !model.pinned[i])
            .map(|i| {
                model.masses[i] * (dx[i][0] * dx[i][0] + dx[i][1] * dx[i][1] + dx[i][2] * dx[i][2])
            })
            .sum();
        let mut stiff = 0.0;
        for (e, t) in model.mesh.tets().iter().enumerate() {
            let g = shape_gradients(model, e);
            let mut df = [[0.0; 3]; 3];
            for (k, &v) in t.iter().enumerate() {
                if model.pinned[v] {
                    continue;
                }
                for a in 0..3 {
                    for b in 0..3 {
                        df[a][b] += dx[v][a] * g[k][b];
                    }
                }
            }
            let f2: f64 = df.iter().flatten().map(|q| q * q).sum();
            stiff += 2.0 * mu * model.rest_volume[e] * f2;
        }
        mass + h * h * stiff
    }
}

/// Free vertices per parallel task of the right-hand side assembly.
const RHS_CHUNK: usize = 256;

impl Integrator for ProjectiveDynamics {
    fn name(&self) -> &'static str {
        "projective_dynamics"
    }

    fn is_implicit(&self) -> bool {
        true
    }

    fn set_obstacles(&mut self, obstacles: &[Obstacle]) {
        self.contact = ContactPotential::new(obstacles);
    }

    fn check(&self, model: &Model) -> Result<()> {
        match model.material {
            Material::Arap(_) => Ok(()),
            _ => Err(invalid(
                "material",
                "projective_dynamics minimises the PD (ARAP) energy; give the Arap material so that FEPR conserves \
                 that energy",
            )),
        }
    }

    // The PD step as the paper states it, in three parts so that several bodies can take their iterations
    // together (contact between bodies inside their solves, [`CoupledSolve`]): `begin` (prefactor on change,
    // the prediction, the contact set), `iterate` (one local and global step), `finish` (velocities and the
    // contacts' report).
    fn step(
        &mut self,
        model: &Model,
        state: &mut State,
        h: f64,
        hand_over: &mut HandOver,
    ) -> StepReport {
        hand_over.share_metric(&(Arc::clone(&self.matrix) as SharedMetric));
        self.begin_step(model, state, h);
        for it in 0..self.settings.iterations {
            self.solve_unconstrained(model);
            if self.accept_solution(model, it) {
                break;
            }
        }
        self.finish_step(model, state, h)
    }

    fn coupled(&mut self) -> Option<&mut dyn CoupledSolve> {
        Some(self)
    }
}

impl CoupledSolve for ProjectiveDynamics {
    fn begin(&mut self, model: &Model, state: &State, h: f64, hand_over: &mut HandOver) {
        hand_over.share_metric(&(Arc::clone(&self.matrix) as SharedMetric));
        self.begin_step(model, state, h);
        self.together = true;
    }

    fn contacts_grew(&self) -> bool {
        self.set_grew
    }

    fn iterations(&self) -> usize {
        if self.failed {
            0
        } else {
            self.settings.iterations
        }
    }

    fn positions(&self) -> &[Vec3] {
        &self.x
    }

    fn solve(&mut self, model: &Model) {
        self.solve_unconstrained(model);
    }

    fn free_vertices(&self) -> Vec<usize> {
        let matrix = self.matrix.lock().unwrap_or_else(|e| e.into_inner());
        matrix
            .pre
            .as_ref()
            .map_or_else(Vec::new, |p| p.free_vertices.clone())
    }

    fn solution_mut(&mut self) -> &mut [Vec3] {
        &mut self.rhs
    }

    fn solve_columns(&mut self, columns: &mut [f64], count: usize) {
        let mut matrix = self.matrix.lock().unwrap_or_else(|e| e.into_inner());
        let pre = matrix.pre.as_mut().expect("begun");
        match (&mut pre.contact, self.active.is_empty()) {
            (Some((chol, _)), false) => chol.solve_many_in_place(columns, count),
            _ => pre.chol.solve_many_in_place(columns, count),
        }
    }

    fn matrix_version(&self) -> usize {
        self.factorizations * 2 + usize::from(self.active.is_empty())
    }

    fn accept(&mut self, model: &Model, it: usize) -> bool {
        self.accept_solution(model, it)
    }

    fn finish(&mut self, model: &Model, state: &mut State, h: f64) -> StepReport {
        self.finish_step(model, state, h)
    }
}

impl ProjectiveDynamics {
    /// The step's start: the matrix (factorised again when `h` or the model changed), the inertial prediction
    /// and the contact constraints' active set. A failure (only a singular matrix or a wrong material, which
    /// `check` refuses) is remembered: the iterations do nothing and [`Self::finish_step`] poisons the state.
    fn begin_step(&mut self, model: &Model, state: &State, h: f64) {
        // Moving obstacles where they are over this step (the constraints hold the vertices at the step's end).
        self.contact.place(state.time, h);
        self.failed = false;
        self.together = false;
        self.set_grew = false;
        self.timing = PdTiming::default();
        self.refreshes = 0;
        let mut matrix = self.matrix.lock().unwrap_or_else(|e| e.into_inner());
        // The matrix depends on h, the masses, the pins and the material's mu: refactorise when the simulation
        // changes h (impact substeps) or the model changed since the factorisation (a user of the Rust API may
        // change `Model`'s public fields between steps, or step this integrator with another model).
        if matrix.pre.is_some() {
            let key = model.key();
            if matrix
                .pre
                .as_ref()
                .is_some_and(|p| p.h != h || p.key != key)
            {
                matrix.pre = None;
            }
        }
        if matrix.pre.is_none() {
            match Self::prefactor(model, h) {
                Ok(p) => {
                    matrix.pre = Some(p);
                    self.factorizations += 1;
                }
                Err(_) => {
                    self.failed = true;
                    return;
                }
            }
        }
        let pre = matrix.pre.as_mut().expect("prefactored");
        let m = model.num_vertices();
        let inv_h2 = 1.0 / (h * h);
        // Workspaces (no allocation in the step loop): the start positions, the iterate (from the inertial
        // prediction with gravity) and the inertial target y = x_n + h v_n.
        let (x_n, x, y) = (&mut self.x_n, &mut self.x, &mut self.y);
        x_n.clone_from(&state.x);
        y.clear();
        x.clear();
        for i in 0..m {
            if model.pinned[i] {
                y.push(state.x[i]);
                x.push(state.x[i]);
            } else {
                y.push([0, 1, 2].map(|a| state.x[i][a] + h * state.v[i][a]));
                x.push(
                    [0, 1, 2].map(|a| state.x[i][a] + h * state.v[i][a] + h * h * model.gravity[a]),
                );
            }
        }
        self.report = StepReport {
            impulse: scale(model.gravity, h * model.free_mass()),
            ..Default::default()
        };
        self.step_h = h;
        // The contact constraints' active set: the free vertices the inertial prediction puts inside an obstacle.
        self.active.clear();
        match Self::extend_active_set(&self.contact, &mut self.active, pre, model, x, inv_h2) {
            Ok(factorized) => self.factorizations += factorized as usize,
            Err(_) => {
                // Cannot happen for a positive definite matrix plus positive diagonal weights; poison the state
                // as for the plain matrix so that the simulation reports it.
                self.failed = true;
                return;
            }
        }
        // The first local step starts from the prediction with the active vertices on the surface (their
        // constraints' targets), not from deep inside the obstacle, which would strain the elements around them.
        for &v in &self.active {
            x[v] = self.contact.nearest_outside(model, x[v]);
        }
        self.corner_terms.resize(model.num_tets(), [[0.0; 3]; 4]);
    }

    /// The local step and the global solve of one iteration, with the contact constraints of the obstacles,
    /// leaving the solution in `self.rhs` (one row per free vertex) for [`Self::accept_solution`] (between them, contact
    /// between bodies may correct it, [`CoupledSolve`]).
    fn solve_unconstrained(&mut self, model: &Model) {
        if self.failed {
            return;
        }
        let h = self.step_h;
        let inv_h2 = 1.0 / (h * h);
        let mut matrix = self.matrix.lock().unwrap_or_else(|e| e.into_inner());
        let pre = matrix.pre.as_mut().expect("begun");
        let n = pre.free_vertices.len();
        let (x, y) = (&self.x, &self.y);
        let t0 = Instant::now();
        // Local step: the closest rotation R_e to each F_e and its corner terms w_e R_e g_k, in parallel
        // (rotation_blocks: bit for bit linalg::polar_rotation).
        crate::elasticity::pd_rotation_terms(pre.mu, model, x, &mut self.corner_terms);
        let t1 = Instant::now();
        // Global step right-hand side, row c for free vertex c: M (y / h^2 + g) + sum_e w_e R_e g_e,k over
        // the tets at the vertex, gathered in parallel in ascending block position (deterministic).
        let terms = self.corner_terms.as_flattened();
        let g = model.gravity;
        self.rhs.resize(n, [0.0; 3]);
        for_each_chunk_mut(&mut self.rhs, RHS_CHUNK, |ci, chunk| {
            for (k, out) in chunk.iter_mut().enumerate() {
                let v = pre.free_vertices[ci * RHS_CHUNK + k];
                let mut acc = [0.0; 3];
                for a in 0..3 {
                    acc[a] = model.masses[v] * (inv_h2 * y[v][a] + g[a]);
                }
                let r = model.kernel_rank[v] as usize;
                let slots = &model.incidence_slots
                    [model.incidence_offsets[r]..model.incidence_offsets[r + 1]];
                for &slot in slots {
                    let t = terms[slot as usize];
                    for a in 0..3 {
                        acc[a] += t[a];
                    }
                }
                *out = acc;
            }
        });
        for &(row, p, coef) in &pre.pinned_coupling {
            for a in 0..3 {
                self.rhs[row][a] -= coef * x[p][a];
            }
        }
        // Contact constraints: each active vertex pulled to the contact layer from where one Jacobi step of the
        // unconstrained equations `A x = b` takes its iterate (`x + (b - A x)_v / A_vv`, then out of the
        // obstacles, with Coulomb friction on the move along the surface: `ContactPotential::friction_target`).
        // Why not from the iterate itself: the constraint's weight (a thousand times the vertex's inertia) then
        // holds the vertex where the iteration started it in every direction, the tangential ones included, and
        // ten iterations move it a hundredth of the way the elastic forces pull it: a box resting in a corner had
        // its face along the wall in free fall (an inertial prediction the constraints kept), and its elastic
        // energy grew from 0 to 5.6 J in 10 steps. The Jacobi step lets the elastic forces move it along the
        // surface where friction does not hold it, and the obstacle takes back only the normal part.
        self.targets.clear();
        if !self.active.is_empty() {
            residual_rows(pre, x, &self.rhs, &mut self.residual);
        }
        for &v in &self.active {
            let c = pre.free_vertices.partition_point(|&f| f < v);
            let jacobi = scale(self.residual[c], 1.0 / pre.values[pre.diagonal[c]]);
            let target = self.contact.friction_target(model, x[v], jacobi);
            let w = CONTACT_WEIGHT_RATIO * model.masses[v] * inv_h2;
            for a in 0..3 {
                self.rhs[c][a] += w * target[a];
            }
            self.targets.push(target);
        }
        // The set the targets belong to (a later iteration's `accept` may grow the active set).
        self.target_vertices.clone_from(&self.active);
        let t2 = Instant::now();
        match (&mut pre.contact, self.active.is_empty()) {
            (Some((chol, _)), false) => chol.solve3_in_place(&mut self.rhs),
            _ => pre.chol.solve3_in_place(&mut self.rhs),
        }
        let t3 = Instant::now();
        self.timing.local += (t1 - t0).as_secs_f64();
        self.timing.rhs += (t2 - t1).as_secs_f64();
        self.timing.solve += (t3 - t2).as_secs_f64();
    }

    /// The end of iteration `it`: the solution becomes the iterate; vertices the iterations brought into an
    /// obstacle's reach join the active set. Returns true when the positions' relative change is below the
    /// tolerance (or the step failed).
    fn accept_solution(&mut self, model: &Model, it: usize) -> bool {
        if self.failed {
            return true;
        }
        let inv_h2 = 1.0 / (self.step_h * self.step_h);
        let mut matrix = self.matrix.lock().unwrap_or_else(|e| e.into_inner());
        let pre = matrix.pre.as_mut().expect("begun");
        let (x_n, x) = (&self.x_n, &mut self.x);
        let mut change: f64 = 0.0;
        let mut size: f64 = 0.0;
        for (c, &v) in pre.free_vertices.iter().enumerate() {
            for a in 0..3 {
                let new = self.rhs[c][a];
                change = change.max((new - x[v][a]).abs());
                size = size.max((new - x_n[v][a]).abs());
                x[v][a] = new;
            }
        }
        // Vertices that the iterations brought into an obstacle's reach join the active set (at most
        // ACTIVE_SET_REFRESHES times a step, each a numeric factorisation): else they would end the step
        // inside and be pushed out after it, in substeps when deep.
        // Among bodies taking their iterations together the step goes on while contact changes (their rows'
        // corrections push vertices towards the obstacles), so the set may grow more often and at any iteration.
        self.set_grew = false;
        let (limit, later) = if self.together {
            (TOGETHER_REFRESHES, true)
        } else {
            (ACTIVE_SET_REFRESHES, it + 1 < self.settings.iterations)
        };
        if !self.contact.is_empty() && self.refreshes < limit && later {
            match Self::extend_active_set(&self.contact, &mut self.active, pre, model, x, inv_h2) {
                Ok(factorized) => {
                    self.set_grew = factorized;
                    self.refreshes += factorized as usize;
                    self.factorizations += factorized as usize;
                }
                Err(_) => {
                    self.failed = true;
                    return true;
                }
            }
        }
        self.report.iterations = it + 1;
        self.report.residual = if size > 0.0 { change / size } else { 0.0 };
        self.settings
            .tolerance
            .is_some_and(|tol| self.report.residual <= tol)
    }

    /// The step's end: velocities from the final iterate, the obstacles' contacts held in the solve (their
    /// impacts and friction, [`ContactPotential::apply_impacts`]) and the report.
    fn finish_step(&mut self, model: &Model, state: &mut State, h: f64) -> StepReport {
        if self.failed {
            // Only reachable without `check` (wrong material) or a singular matrix: poison the state so that
            // the simulation reports it instead of silently standing still.
            state.x.iter_mut().for_each(|p| *p = [f64::NAN; 3]);
            return StepReport::default();
        }
        let (x, x_n, y) = (&self.x, &self.x_n, &self.y);
        finish_positional_step(model, state, x, x_n, h);
        let mut report = std::mem::take(&mut self.report);
        // The contact impulse of the last global solve: its constraint force w (p - x) at the final iterate.
        let (active, targets, contact) = (&self.target_vertices, &self.targets, &self.contact);
        let v_start = |i: usize| [0, 1, 2].map(|a| (y[i][a] - x_n[i][a]) / h);
        report.contact = contact.apply_impacts(model, state, h, v_start, |i, x| {
            let k = active.binary_search(&i).ok()?;
            let d = [0, 1, 2].map(|a| targets[k][a] - x[a]);
            (d != [0.0; 3]).then(|| scale(d, CONTACT_WEIGHT_RATIO / h))
        });
        report.impulse = add(report.impulse, report.contact.impulse);
        report.angular_impulse = add(report.angular_impulse, report.contact.angular_impulse);
        report
    }
}

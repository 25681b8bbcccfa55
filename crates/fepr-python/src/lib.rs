//! Thin PyO3 bindings of fepr-core (Python module `fepr._core`). Types and conversions only; the public
//! Python API lives in `python/fepr`. `Simulation.step` releases the GIL.

use numpy::ndarray::{Array1, Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

mod sync_floor;

use fepr_core::elasticity::{elastic_energy_gradient, ElasticWorkspace};
use fepr_core::integrators::INTEGRATOR_NAMES;
use fepr_core::invariants::measure;
use fepr_core::material::{Hyperelastic, MATERIAL_NAMES};
use fepr_core::math::Vec3;
use fepr_core::mesh::VertexOrder;
use fepr_core::mesh::{MassSpec, TetMesh};
use fepr_core::model::{ModelBuilder, State};
use fepr_core::projection::{
    report_values, ProjectionReport, Projector, ReportValue, METRIC_NAMES, REPORT_FIELDS,
    ROW_NAMES, SLACK_NAMES, WARM_START_MODES,
};
use fepr_core::simulation::{
    auto_warm_start_threshold, conserved_material_name, history_row, material_for_integrator,
    BodyCoefficients, Simulation as CoreSimulation, HISTORY_COLUMNS, HISTORY_INTEGER_COLUMNS,
    PD_WARM_START, XPBD_WARM_START,
};
use fepr_core::world::{Drag, KinematicPins, PinMotion};
use fepr_core::world::{MeshCollider, Obstacle, ObstacleMotion, Shape};
use fepr_core::FeprError;

mod settings;

/// A kinematic pin group from Python: `(vertices, motion kind, motion parameters, keyframe times)`.
type PinGroupArgs = (Vec<usize>, String, Vec<f64>, Vec<f64>);
/// An obstacle's motion from Python: `(translation kind, its parameters, keyframe times, angular velocity,
/// pivot, orientation times, orientations flattened (k * 3 rotation vectors))`; the translation as a kinematic
/// pin's (`"none"`: no translation).
type ObstacleMotionArgs = (
    String,
    Vec<f64>,
    Vec<f64>,
    [f64; 3],
    [f64; 3],
    Vec<f64>,
    Vec<f64>,
);
/// `(kind, params, restitution, friction, triangles, motion)` of one obstacle (see `set_obstacles`).
type ObstacleArgs = (
    String,
    Vec<f64>,
    f64,
    f64,
    Vec<u32>,
    Option<ObstacleMotionArgs>,
);

/// A translation path from Python (`kind`, parameters, keyframe times; see [`PinGroupArgs`]), `what` naming its
/// owner in the error.
fn pin_motion(kind: &str, p: Vec<f64>, times: Vec<f64>, what: &str) -> PyResult<PinMotion> {
    match kind {
        "sinusoid" if p.len() == 5 => Ok(PinMotion::Sinusoid {
            amplitude: [p[0], p[1], p[2]],
            frequency: p[3],
            phase: p[4],
        }),
        "keyframes" if p.len() == 3 * times.len() => Ok(PinMotion::Keyframes {
            offsets: p.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
            times,
        }),
        _ => Err(PyValueError::new_err(format!(
            "{what}: bad motion {kind:?} with {} parameters",
            p.len()
        ))),
    }
}

/// An obstacle's motion from Python ([`ObstacleMotionArgs`]), `what` naming its owner in the error.
fn obstacle_motion(args: ObstacleMotionArgs, what: &str) -> PyResult<ObstacleMotion> {
    let (path, q, times, angular_velocity, pivot, turn_times, turns) = args;
    if turns.len() != 3 * turn_times.len() {
        return Err(PyValueError::new_err(format!(
            "{what}: orientations must be one rotation vector (3 numbers) per time, got {} numbers for {} times",
            turns.len(),
            turn_times.len()
        )));
    }
    let translation = if path == "none" {
        PinMotion::Keyframes {
            times: vec![0.0],
            offsets: vec![[0.0; 3]],
        }
    } else {
        pin_motion(&path, q, times, what)?
    };
    Ok(ObstacleMotion {
        translation,
        angular_velocity,
        pivot,
        orientations: (
            turn_times,
            turns.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
        ),
    })
}

/// Where an obstacle with `motion` ([`ObstacleMotionArgs`]) is at time `t` (s), as the core places it:
/// `(R (3, 3) rows, offset (3,) m)` with `x = R p + offset` for a point `p` of the obstacle as given.
#[pyfunction]
fn obstacle_placement(motion: ObstacleMotionArgs, t: f64) -> PyResult<([[f64; 3]; 3], [f64; 3])> {
    let motion = obstacle_motion(motion, "ObstacleMotion")?;
    motion
        .validate()
        .map_err(|e| PyValueError::new_err(format!("ObstacleMotion: {e}")))?;
    let pose = motion.pose(t);
    let offset = pose.apply([0.0; 3]);
    // Column c of R is where the unit vector e_c goes, less the offset.
    let mut r = [[0.0; 3]; 3];
    for c in 0..3 {
        let mut e = [0.0; 3];
        e[c] = 1.0;
        let image = pose.apply(e);
        for a in 0..3 {
            r[a][c] = image[a] - offset[a];
        }
    }
    Ok((r, offset))
}

fn value_error(e: FeprError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

fn to_vec3(a: &PyReadonlyArray2<f64>, name: &str) -> PyResult<Vec<Vec3>> {
    let a = a.as_array();
    if a.ncols() != 3 {
        return Err(PyValueError::new_err(format!(
            "{name} must have shape (n, 3), got {:?}",
            a.shape()
        )));
    }
    Ok(a.rows().into_iter().map(|r| [r[0], r[1], r[2]]).collect())
}

/// Internal per-vertex rows as an (m, 3) array in the user's numbering.
fn from_vec3_user<'py>(
    py: Python<'py>,
    order: &VertexOrder,
    v: &[Vec3],
) -> Bound<'py, PyArray2<f64>> {
    let mut a = Array2::<f64>::zeros((v.len(), 3));
    for (u, mut row) in a.rows_mut().into_iter().enumerate() {
        let p = v[order.internal(u)];
        for c in 0..3 {
            row[c] = p[c];
        }
    }
    a.into_pyarray(py)
}

fn build_mesh(
    vertices: &PyReadonlyArray2<f64>,
    tets: &PyReadonlyArray2<i64>,
) -> PyResult<(TetMesh, fepr_core::mesh::MeshReport)> {
    let v = to_vec3(vertices, "vertices")?;
    let t = tets.as_array();
    if t.ncols() != 4 {
        return Err(PyValueError::new_err(format!(
            "tets must have shape (k, 4), got {:?}",
            t.shape()
        )));
    }
    let t: Vec<[i64; 4]> = t
        .rows()
        .into_iter()
        .map(|r| [r[0], r[1], r[2], r[3]])
        .collect();
    TetMesh::new(v, &t).map_err(value_error)
}

/// Validate a mesh; returns (positively oriented tets (k, 4) int64, number flipped, number of unreferenced vertices).
#[pyfunction]
fn validate_mesh<'py>(
    py: Python<'py>,
    vertices: PyReadonlyArray2<'py, f64>,
    tets: PyReadonlyArray2<'py, i64>,
) -> PyResult<(Bound<'py, PyArray2<i64>>, usize, usize)> {
    let (mesh, report) = build_mesh(&vertices, &tets)?;
    let mut out = Array2::<i64>::zeros((mesh.num_tets(), 4));
    for (e, t) in mesh.tets().iter().enumerate() {
        for c in 0..4 {
            out[[e, c]] = t[c] as i64;
        }
    }
    Ok((out.into_pyarray(py), report.flipped, report.unreferenced))
}

/// Energy densities (n,), stresses (n, 3, 3) and optional stress derivatives (n, 9, 9).
type MaterialArrays<'py> = (
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray3<f64>>,
    Option<Bound<'py, PyArray3<f64>>>,
);

/// Evaluate a material at deformation gradients `F` (n, 3, 3): returns energy densities (n,) J/m^3, first
/// Piola stresses (n, 3, 3) Pa and stress derivatives (n, 9, 9) Pa (row-major flattening of F).
#[pyfunction]
#[pyo3(signature = (model, youngs_modulus, poisson_ratio, j0, f, derivative = true))]
fn material_eval<'py>(
    py: Python<'py>,
    model: &str,
    youngs_modulus: f64,
    poisson_ratio: f64,
    j0: f64,
    f: PyReadonlyArray3<'py, f64>,
    derivative: bool,
) -> PyResult<MaterialArrays<'py>> {
    let mat = settings::build_material(model, youngs_modulus, poisson_ratio, j0)?;
    let f = f.as_array();
    if f.shape()[1] != 3 || f.shape()[2] != 3 {
        return Err(PyValueError::new_err(format!(
            "F must have shape (n, 3, 3), got {:?}",
            f.shape()
        )));
    }
    let n = f.shape()[0];
    let mut psi = Array1::<f64>::zeros(n);
    let mut p = Array3::<f64>::zeros((n, 3, 3));
    let mut d = derivative.then(|| Array3::<f64>::zeros((n, 9, 9)));
    for k in 0..n {
        let mut fk = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                fk[i][j] = f[[k, i, j]];
            }
        }
        let (e, pk) = mat.energy_and_stress(&fk);
        psi[k] = e;
        for i in 0..3 {
            for j in 0..3 {
                p[[k, i, j]] = pk[i][j];
            }
        }
        if let Some(d) = d.as_mut() {
            let dk = mat.stress_derivative(&fk);
            for a in 0..9 {
                for b in 0..9 {
                    d[[k, a, b]] = dk[a][b];
                }
            }
        }
    }
    Ok((
        psi.into_pyarray(py),
        p.into_pyarray(py),
        d.map(|d| d.into_pyarray(py)),
    ))
}

// From Python the model is fixed once built: no method here writes `inner.model` (the world setters change the
// core's `World`, the state setters the `State`), so the integrators' and the projection's cached data built
// from the model (factorisations, patterns, the stiffness metric) cannot go stale through this module. The core
// keys that data on `Model::key` / `Model::structure_key` all the same (the Rust API lets users change the
// model's public fields between steps), so a method added here that changes the model needs nothing more.
/// The simulation: model, state, integrator and projection (see `fepr.Simulation` for the documented API), on
/// the mesh renumbered in a locality order; every per-vertex array in and out is in the user's numbering.
#[pyclass(module = "fepr._core")]
struct Simulation {
    inner: CoreSimulation,
    threads: Threads,
    /// The core runs on the mesh renumbered in a locality order (`fepr_core::mesh`: two threads share
    /// their cores' caches better); every per-vertex array crossing this boundary is translated, so Python
    /// sees the user's numbering.
    order: VertexOrder,
}

/// Where a simulation's steps and measurements run (its `threads` argument).
enum Threads {
    /// No count given: the global pool (all cores), entered once per `step(n)` call (`parallel::on_pool`).
    Global,
    /// One thread: the calling thread itself, without a pool (`parallel::serial`): a pool's only thread would
    /// be woken for every call and park after it.
    Serial,
    /// Two or more: a pool of its own.
    Pool(rayon::ThreadPool),
}

impl Threads {
    fn new(threads: Option<usize>) -> PyResult<Self> {
        Ok(match threads {
            None => Self::Global,
            Some(0) => return Err(PyValueError::new_err("threads: must be at least 1")),
            Some(1) => Self::Serial,
            Some(n) => Self::Pool(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build()
                    .map_err(|e| {
                        PyRuntimeError::new_err(format!("cannot start {n} threads: {e}"))
                    })?,
            ),
        })
    }

    /// `f()` on these threads.
    fn run<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        match self {
            Self::Global => fepr_core::exec::on_pool(f),
            Self::Serial => fepr_core::exec::serial(f),
            Self::Pool(pool) => pool.install(f),
        }
    }
}

fn report_dict<'py>(py: Python<'py>, r: &ProjectionReport) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for (name, value) in REPORT_FIELDS.iter().zip(report_values(r)) {
        match value {
            ReportValue::Count(n) => d.set_item(name, n)?,
            ReportValue::Flag(b) => d.set_item(name, b)?,
            ReportValue::Real(x) => d.set_item(name, x)?,
        }
    }
    Ok(d)
}

#[pymethods]
impl Simulation {
    /// Settings cross as one dict per concern, each checked once here and in the core (`settings`): errors
    /// name the key as `section.key`. `material`: model, youngs_modulus, poisson_ratio, j0; `mass`: exactly one
    /// of density (kg/m^3), node_mass (kg per vertex), node_masses ((m,) kg); `integrator`: name and its
    /// settings; `projection`: the fields of `fepr.Projection`, or None for no projection; `world`: gravity,
    /// pinned, damping. Under the integrators that fix the energy they minimise (Projective Dynamics, XPBD)
    /// the material is that energy's, built from the given moduli (`fepr_core::simulation::
    /// material_for_integrator`).
    #[new]
    #[pyo3(signature = (vertices, tets, *, material, mass, integrator, dt, projection, world, threads = None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        vertices: PyReadonlyArray2<'_, f64>,
        tets: PyReadonlyArray2<'_, i64>,
        material: &Bound<'_, PyAny>,
        mass: &Bound<'_, PyAny>,
        integrator: &Bound<'_, PyAny>,
        dt: f64,
        projection: Option<&Bound<'_, PyAny>>,
        world: &Bound<'_, PyAny>,
        threads: Option<usize>,
    ) -> PyResult<Self> {
        let (model_name, youngs_modulus, poisson_ratio, j0) = settings::material(material)?;
        let choice = settings::integrator(integrator)?;
        let projection = projection.map(settings::projection).transpose()?;
        let (gravity, pinned, damping) = settings::world(world)?;
        let mass = {
            let s = settings::Section::new("mass", mass, &["density", "node_mass", "node_masses"])?;
            let given = ["density", "node_mass", "node_masses"]
                .iter()
                .filter(|k| mass.get_item(**k).is_ok_and(|v| !v.is_none()))
                .count();
            if given != 1 {
                return Err(PyValueError::new_err(
                    "mass: give exactly one of density (kg/m^3), node_mass (kg per vertex) and node_masses",
                ));
            }
            if let Some(v) = s.opt_real("density")? {
                MassSpec::Density(v)
            } else if let Some(v) = s.opt_real("node_mass")? {
                MassSpec::NodeMass(v)
            } else {
                let a: PyReadonlyArray1<'_, f64> =
                    mass.get_item("node_masses")?.extract().map_err(|_| {
                        PyValueError::new_err("mass.node_masses must be a float64 array (m,)")
                    })?;
                MassSpec::PerVertex(a.as_array().to_vec())
            }
        };
        let (user_mesh, _) = build_mesh(&vertices, &tets)?;
        let mat = material_for_integrator(
            choice.name(),
            &model_name,
            youngs_modulus,
            poisson_ratio,
            j0,
        )
        .map_err(|e| PyValueError::new_err(format!("material.{e}")))?;
        let build = |mesh: TetMesh, mass: MassSpec, pinned: Vec<usize>| {
            ModelBuilder::new(mesh, mat)
                .mass(mass)
                .gravity(gravity)
                .pinned(pinned)
                .damping(damping)
                .build()
        };
        let order = VertexOrder::locality(user_mesh.vertices());
        let m = order.len();
        let internal_mass = match &mass {
            MassSpec::PerVertex(v) if v.len() == m => MassSpec::PerVertex(order.to_internal(v)),
            other => other.clone(),
        };
        // Out-of-range indices stay as they are (the build names them).
        let internal_pinned = pinned.iter().map(|&u| order.internal_or_same(u)).collect();
        let internal_mesh = order.mesh(&user_mesh);
        // Freed before the model is built (1M tets: 36 MB less at the peak).
        drop(user_mesh);
        let model = match build(internal_mesh, internal_mass, internal_pinned) {
            Ok(model) => model,
            // Built again in the user's numbering, so that the error names the user's vertices.
            Err(err) => {
                let (user_mesh, _) = build_mesh(&vertices, &tets)?;
                return Err(value_error(
                    build(user_mesh, mass, pinned).err().unwrap_or(err),
                ));
            }
        };
        let integ = choice.build().map_err(value_error)?;
        let projector = match projection {
            Some(p) => Some(Projector::new(p.settings_for(choice.name())).map_err(value_error)?),
            None => None,
        };
        let threads = Threads::new(threads)?;
        let state = State::at_rest(&model);
        let inner = CoreSimulation::new(model, state, integ, dt, projector).map_err(value_error)?;
        Ok(Self {
            inner,
            threads,
            order,
        })
    }

    /// Take up to `n` steps with the GIL released; with `max_seconds`, stop after the first step that ends later
    /// than that after the call began (so that the caller can check for signals and take the history between
    /// bounded batches). Raises RuntimeError (naming the step) on a runaway to a non-finite state. Returns the
    /// number of steps taken.
    #[pyo3(signature = (n, max_seconds=None))]
    fn step(&mut self, py: Python<'_>, n: usize, max_seconds: Option<f64>) -> PyResult<usize> {
        let Self { inner, threads, .. } = self;
        let budget = max_seconds.unwrap_or(f64::INFINITY);
        // Onto the threads once for the whole batch.
        let result = py.detach(|| {
            threads.run(|| -> Result<usize, FeprError> {
                let t0 = std::time::Instant::now();
                for k in 0..n {
                    inner.step()?;
                    if t0.elapsed().as_secs_f64() > budget {
                        return Ok(k + 1);
                    }
                }
                Ok(n)
            })
        });
        result.map_err(|e| PyRuntimeError::new_err(e.to_string()))
    }

    /// What the next steps depend on besides the settings (`fepr_core::simulation::Simulation::carry`), as named
    /// float64 arrays (internal vertex order: only [`Simulation::resume`] of the same settings reads them).
    fn carry<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (name, values) in self.inner.carry().entries() {
            d.set_item(name, values.clone().into_pyarray(py))?;
        }
        Ok(d)
    }

    /// Put back a [`Simulation::carry`] taken from a simulation with the same settings; ValueError names what
    /// does not match.
    fn resume(&mut self, carry: std::collections::BTreeMap<String, Vec<f64>>) -> PyResult<()> {
        self.inner
            .resume(&fepr_core::checkpoint::Carry::from_entries(carry))
            .map_err(value_error)
    }

    /// The history rows of the steps after `step` as a (rows, columns) float64 array (see `history_columns()`).
    fn history_after<'py>(&self, py: Python<'py>, step: i64) -> Bound<'py, PyArray2<f64>> {
        let h = self.inner.history();
        let first = h.partition_point(|d| (d.step as i64) <= step);
        rows_array(py, &h[first..])
    }

    /// Drop every history row but the last (the caller has taken them with `history_after`).
    fn trim_history(&mut self) {
        self.inner.trim_history();
    }

    #[getter]
    fn positions<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        from_vec3_user(py, &self.order, &self.inner.state.x)
    }
    #[setter]
    fn set_positions(&mut self, x: PyReadonlyArray2<'_, f64>) -> PyResult<()> {
        let x = self.checked_state_array(&x, "positions")?;
        self.inner.state.x = x;
        self.inner.reset_references();
        Ok(())
    }
    #[getter]
    fn velocities<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        from_vec3_user(py, &self.order, &self.inner.state.v)
    }
    #[setter]
    fn set_velocities(&mut self, v: PyReadonlyArray2<'_, f64>) -> PyResult<()> {
        let mut v = self.checked_state_array(&v, "velocities")?;
        for (vi, p) in v.iter_mut().zip(&self.inner.model.pinned) {
            if *p {
                *vi = [0.0; 3];
            }
        }
        self.inner.state.v = v;
        self.inner.reset_references();
        Ok(())
    }
    #[getter]
    fn time(&self) -> f64 {
        self.inner.state.time
    }
    #[getter]
    fn num_steps(&self) -> usize {
        self.inner.num_steps()
    }
    #[getter]
    fn dt(&self) -> f64 {
        self.inner.dt()
    }
    #[getter]
    fn integrator(&self) -> &'static str {
        self.inner.integrator_name()
    }
    #[getter]
    fn masses<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        Array1::from(self.order.to_user(&self.inner.model.masses)).into_pyarray(py)
    }
    #[getter]
    fn total_mass(&self) -> f64 {
        self.inner.model.total_mass
    }
    #[getter]
    fn length_scale(&self) -> f64 {
        self.inner.model.length_scale
    }
    #[getter]
    fn rest_positions<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        from_vec3_user(py, &self.order, self.inner.model.mesh.vertices())
    }
    #[getter]
    fn pinned<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<bool>> {
        Array1::from(self.order.to_user(&self.inner.model.pinned)).into_pyarray(py)
    }

    /// (kinetic, elastic, gravitational, total, min_j, inverted) of the current state.
    fn measure(&self, py: Python<'_>) -> (f64, f64, f64, f64, f64, usize) {
        let i = self.measured(py);
        (
            i.kinetic,
            i.elastic,
            i.gravitational,
            i.total,
            i.min_j,
            i.inverted,
        )
    }
    /// (P, L about the centre of mass, centre of mass), each a 3-tuple.
    fn momenta(&self, py: Python<'_>) -> ([f64; 3], [f64; 3], [f64; 3]) {
        let i = self.measured(py);
        (i.momentum, i.angular_momentum, i.center_of_mass)
    }
    /// Elastic energy (J) and its gradient (m, 3) J/m at positions `x` (m, 3).
    fn elastic_energy_gradient<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<(f64, Bound<'py, PyArray2<f64>>)> {
        let x = self.checked_state_array(&x, "x")?;
        let mut grad = vec![[0.0; 3]; x.len()];
        let (model, threads) = (&self.inner.model, &self.threads);
        let s = py.detach(|| {
            threads.run(|| {
                elastic_energy_gradient(model, &x, &mut ElasticWorkspace::default(), &mut grad)
            })
        });
        Ok((s.energy, from_vec3_user(py, &self.order, &grad)))
    }
    /// Benchmark helper: the same elastic energy + gradient evaluation run by `copies` threads at once, each
    /// on a one-thread pool of its own with its own workspace and gradient (they share only the read-only model
    /// and positions), `repeats` evaluations each in up to ten batches that all copies start together. Returns
    /// seconds per evaluation: the slowest copy's time in the best batch. Against one copy alone
    /// (`bench_energy_gradient(repeats, 1)`), `copies` times that ratio is the machine's throughput gain for
    /// this evaluation with nothing to synchronise: the ceiling over the `copies`-thread speed-up. On a virtual
    /// machine whose virtual CPUs share their host's cores with other guests it is below `copies` (measured
    /// on two threads here: 1.9-2.1 in calm spells, 1.2-1.4 in busy ones).
    fn bench_energy_gradient_apart(
        &self,
        py: Python<'_>,
        repeats: usize,
        copies: usize,
    ) -> PyResult<f64> {
        if repeats == 0 || copies == 0 {
            return Err(PyValueError::new_err(
                "repeats and copies must be at least 1",
            ));
        }
        let pools = (0..copies)
            .map(|_| rayon::ThreadPoolBuilder::new().num_threads(1).build())
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| PyRuntimeError::new_err(format!("cannot start {copies} threads: {e}")))?;
        let (model, x) = (&self.inner.model, &self.inner.state.x);
        let batches = repeats.min(10);
        // One spinning start line per batch (a sleeping barrier wakes its threads tens of microseconds apart on
        // a virtual machine, a good part of a small mesh's batch, in which one copy would run alone).
        let start: Vec<std::sync::atomic::AtomicUsize> = (0..batches)
            .map(|_| std::sync::atomic::AtomicUsize::new(0))
            .collect();
        let per_copy: Vec<Vec<f64>> = py.detach(|| {
            std::thread::scope(|scope| {
                let handles: Vec<_> = pools
                    .iter()
                    .map(|pool| {
                        let start = &start;
                        scope.spawn(move || {
                            pool.install(|| {
                                let mut grad = vec![[0.0; 3]; x.len()];
                                let mut ws = ElasticWorkspace::default();
                                let warm = std::time::Instant::now();
                                while warm.elapsed().as_secs_f64() < 0.02 {
                                    elastic_energy_gradient(model, x, &mut ws, &mut grad);
                                }
                                (0..batches)
                                    .map(|b| {
                                        let n =
                                            repeats / batches + usize::from(b < repeats % batches);
                                        use std::sync::atomic::Ordering::{AcqRel, Acquire};
                                        start[b].fetch_add(1, AcqRel);
                                        let mut spins = 0u32;
                                        while start[b].load(Acquire) < copies {
                                            spins += 1;
                                            if spins < 100_000 {
                                                std::hint::spin_loop();
                                            } else {
                                                std::thread::yield_now();
                                            }
                                        }
                                        let t0 = std::time::Instant::now();
                                        for _ in 0..n {
                                            elastic_energy_gradient(model, x, &mut ws, &mut grad);
                                        }
                                        t0.elapsed().as_secs_f64() / n as f64
                                    })
                                    .collect()
                            })
                        })
                    })
                    .collect();
                handles
                    .into_iter()
                    .map(|h| h.join().expect("a copy panicked"))
                    .collect()
            })
        });
        let slowest = |b: usize| per_copy.iter().map(|c| c[b]).fold(0.0, f64::max);
        Ok((0..batches).map(slowest).fold(f64::INFINITY, f64::min))
    }
    /// Benchmark helper: time `repeats` elastic energy + gradient evaluations at the current positions on
    /// `threads` worker threads (GIL released, workspace reused, after one warm-up evaluation), in up to ten
    /// batches; the best batch's mean is the time (interference from other processes only ever adds).
    /// `awake`: time them as in a step, with the pool's other threads kept ready between evaluations
    /// (`fepr_core::exec::with_threads_ready`); else cold, each evaluation waking parked threads. Returns
    /// (seconds per evaluation, the energy's bits, a checksum of the gradient's bits) so callers can
    /// compare thread counts bit for bit.
    #[pyo3(signature = (repeats, threads, awake = false))]
    fn bench_energy_gradient(
        &self,
        py: Python<'_>,
        repeats: usize,
        threads: usize,
        awake: bool,
    ) -> PyResult<(f64, u64, u64)> {
        if repeats == 0 || threads == 0 {
            return Err(PyValueError::new_err(
                "repeats and threads must be at least 1",
            ));
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .map_err(|e| PyRuntimeError::new_err(format!("cannot start {threads} threads: {e}")))?;
        let (model, x) = (&self.inner.model, &self.inner.state.x);
        Ok(py.detach(|| {
            pool.install(|| {
                let timed = || {
                    let mut grad = vec![[0.0; 3]; x.len()];
                    let mut ws = ElasticWorkspace::default();
                    let mut s = elastic_energy_gradient(model, x, &mut ws, &mut grad);
                    // A fresh pool's threads take up to a few milliseconds to start helping on a virtual machine
                    // (measured: a 1,296-tet mesh ran at one thread's speed through 50 evaluations in most fresh
                    // pools); a simulation's pool lives across steps, so warm this one up before timing it.
                    let warm = std::time::Instant::now();
                    while warm.elapsed().as_secs_f64() < 0.02 {
                        s = elastic_energy_gradient(model, x, &mut ws, &mut grad);
                    }
                    let batches = repeats.min(10);
                    let mut best = f64::INFINITY;
                    for b in 0..batches {
                        let n = repeats / batches + usize::from(b < repeats % batches);
                        let t0 = std::time::Instant::now();
                        for _ in 0..n {
                            s = elastic_energy_gradient(model, x, &mut ws, &mut grad);
                        }
                        best = best.min(t0.elapsed().as_secs_f64() / n as f64);
                    }
                    let checksum = grad.iter().flatten().fold(0u64, |h, g| {
                        (h ^ g.to_bits()).wrapping_mul(0x0100_0000_01b3)
                    });
                    (best, s.energy.to_bits(), checksum)
                };
                if awake {
                    fepr_core::exec::with_threads_ready(timed)
                } else {
                    timed()
                }
            })
        }))
    }
    fn last_projection<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        match self.inner.history().last().and_then(|d| d.projection) {
            Some(r) => Ok(Some(report_dict(py, &r)?)),
            None => Ok(None),
        }
    }
    /// First step at or after `start` whose `runaway` flag is set (None if none): lets Python check each
    /// batch of steps without rebuilding the whole history.
    fn first_runaway(&self, start: usize) -> Option<usize> {
        self.inner
            .history()
            .iter()
            .filter(|d| d.step >= start)
            .find(|d| d.runaway)
            .map(|d| d.step)
    }

    /// First step at or after `start` whose projection did not converge (None if none).
    fn first_unconverged(&self, start: usize) -> Option<usize> {
        self.inner
            .history()
            .iter()
            .filter(|d| d.step >= start)
            .find(|d| d.projection.is_some_and(|p| !p.converged && !p.stood_down))
            .map(|d| d.step)
    }

    /// `(unresolved, lost, scale)`: the energy booked as unresolved so far, the energy the base steps lost
    /// against their targets and the run's initial energy scale, J (see
    /// `fepr_core::simulation::Simulation::unresolved_energy`).
    fn unresolved_energy(&self) -> (f64, f64, f64) {
        self.inner.unresolved_energy()
    }

    /// A time step that resolves the body's fast elastic modes, s (a tenth of a pressure wave's crossing time).
    fn resolving_time_step(&self) -> f64 {
        self.inner.resolving_time_step()
    }

    /// Obstacles as `(kind, params, restitution, friction, triangles)`: `"plane"` [point, normal], `"sphere"`
    /// [center, radius], `"box"` [center, half_extents, 9 rotation entries (rows)], `"capsule"` [a, b, radius],
    /// `"mesh"` [vertex coordinates, flattened (n * 3)] with `triangles` its vertex indices flattened (k * 3);
    /// m. `triangles` is empty for the other kinds. `motion`: None (static) or `(translation kind, parameters,
    /// times, angular velocity rad/s, pivot m)` ([`ObstacleMotionArgs`]).
    fn set_obstacles(&mut self, obstacles: Vec<ObstacleArgs>) -> PyResult<()> {
        let mut out = Vec::with_capacity(obstacles.len());
        for (k, (kind, p, restitution, friction, triangles, motion)) in
            obstacles.into_iter().enumerate()
        {
            let need = match kind.as_str() {
                "plane" => 6,
                "sphere" => 4,
                "box" => 15,
                "capsule" => 7,
                "mesh" => p.len() - p.len() % 3,
                _ => {
                    return Err(PyValueError::new_err(format!(
                        "obstacle {k}: unknown type {kind:?} (known: plane, sphere, box, capsule, mesh)"
                    )))
                }
            };
            if p.len() != need {
                return Err(PyValueError::new_err(format!(
                    "obstacle {k} ({kind}): needs {need} parameters, got {}",
                    p.len()
                )));
            }
            if (kind == "mesh") == triangles.is_empty() || !triangles.len().is_multiple_of(3) {
                return Err(PyValueError::new_err(format!(
                    "obstacle {k} ({kind}): triangles must be given (3 indices each) for a mesh and only for a mesh"
                )));
            }
            let v = |i: usize| [p[i], p[i + 1], p[i + 2]];
            let shape = match kind.as_str() {
                "plane" => Shape::Plane {
                    point: v(0),
                    normal: v(3),
                },
                "sphere" => Shape::Sphere {
                    center: v(0),
                    radius: p[3],
                },
                "box" => Shape::Box {
                    center: v(0),
                    half_extents: v(3),
                    axes: [v(6), v(9), v(12)],
                },
                "mesh" => {
                    let vertices: Vec<[f64; 3]> = (0..p.len() / 3).map(|i| v(3 * i)).collect();
                    let tris: Vec<[u32; 3]> = triangles
                        .chunks_exact(3)
                        .map(|t| [t[0], t[1], t[2]])
                        .collect();
                    Shape::Mesh(MeshCollider::new(&vertices, &tris).map_err(|e| {
                        PyValueError::new_err(format!("obstacle {k} ({kind}): {e}"))
                    })?)
                }
                _ => Shape::Capsule {
                    a: v(0),
                    b: v(3),
                    radius: p[6],
                },
            };
            let mut ob = Obstacle::new(shape, restitution, friction)
                .map_err(|e| PyValueError::new_err(format!("obstacle {k} ({kind}): {e}")))?;
            if let Some(args) = motion {
                let what = format!("obstacle {k} ({kind})");
                ob = ob
                    .with_motion(obstacle_motion(args, &what)?)
                    .map_err(|e| PyValueError::new_err(format!("{what}: {e}")))?;
            }
            out.push(ob);
        }
        self.inner.set_obstacles(out);
        Ok(())
    }

    /// Contact of the body with itself: `(restitution, friction)`, or None for off.
    fn set_self_contact(&mut self, coefficients: Option<(f64, f64)>) -> PyResult<()> {
        let c = coefficients
            .map(|(e, mu)| BodyCoefficients::new(e, mu))
            .transpose()
            .map_err(|e| PyValueError::new_err(format!("self_contact: {e}")))?;
        self.inner.set_self_contact(c);
        Ok(())
    }

    /// Kinematic pin groups `(vertices, kind, params, times)`: `"sinusoid"` params [amplitude (3), frequency
    /// Hz, phase rad]; `"keyframes"` params = offsets flattened (k * 3, m) with `times` (k, s).
    fn set_kinematic_pins(&mut self, groups: Vec<PinGroupArgs>) -> PyResult<()> {
        let mut pins = Vec::with_capacity(groups.len());
        for (k, (vertices, kind, p, times)) in groups.into_iter().enumerate() {
            let motion = pin_motion(&kind, p, times, &format!("kinematic pin group {k}"))?;
            let vertices = vertices
                .iter()
                .map(|&u| self.order.internal_or_same(u))
                .collect();
            pins.push(KinematicPins { vertices, motion });
        }
        self.inner.set_kinematic_pins(pins).map_err(value_error)
    }

    /// Air (mass-proportional, 1/s) and Rayleigh (stiffness-proportional, s) damping.
    fn set_damping(&mut self, air: f64, rayleigh: f64) -> PyResult<()> {
        self.inner.set_damping(air, rayleigh).map_err(value_error)
    }

    /// Constant external force per vertex, (m, 3) N; None removes it.
    fn set_external_forces(&mut self, forces: Option<PyReadonlyArray2<'_, f64>>) -> PyResult<()> {
        let f = match forces {
            Some(a) => self.checked_state_array(&a, "external_forces")?,
            None => Vec::new(),
        };
        self.inner.set_external_forces(f).map_err(value_error)
    }

    /// The drag spring `(vertex, target (3,) m, stiffness N/m)`, or None to release it.
    fn set_drag(&mut self, drag: Option<(usize, [f64; 3], f64)>) -> PyResult<()> {
        let d = drag.map(|(vertex, target, stiffness)| Drag {
            vertex: self.order.internal_or_same(vertex),
            target,
            stiffness,
        });
        self.inner.set_drag(d).map_err(value_error)
    }

    #[staticmethod]
    fn history_columns() -> Vec<&'static str> {
        HISTORY_COLUMNS.to_vec()
    }
    /// The diagnostics the core still holds as a (rows, columns) float64 array; see `history_columns()`.
    fn history<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        rows_array(py, self.inner.history())
    }
}

/// Diagnostics rows as a (rows, columns) float64 array.
fn rows_array<'py>(
    py: Python<'py>,
    h: &[fepr_core::simulation::StepDiagnostics],
) -> Bound<'py, PyArray2<f64>> {
    let mut a = Array2::<f64>::zeros((h.len(), HISTORY_COLUMNS.len()));
    for (r, d) in h.iter().enumerate() {
        for (c, v) in history_row(d).iter().enumerate() {
            a[[r, c]] = *v;
        }
    }
    a.into_pyarray(py)
}

impl Simulation {
    /// The invariants of the current state, measured on the simulation's threads (its `threads`: the calling
    /// thread alone for one, its own pool for more, the global pool by default) with the GIL released.
    fn measured(&self, py: Python<'_>) -> fepr_core::invariants::Invariants {
        let (inner, threads) = (&self.inner, &self.threads);
        py.detach(|| threads.run(|| measure(&inner.model, &inner.state)))
    }

    /// A user's (m, 3) per-vertex array, checked (shape, finite rows, named by the user's row), in the internal
    /// numbering.
    fn checked_state_array(
        &self,
        a: &PyReadonlyArray2<'_, f64>,
        name: &str,
    ) -> PyResult<Vec<Vec3>> {
        let m = self.inner.model.num_vertices();
        let v = to_vec3(a, name)?;
        if v.len() != m {
            return Err(PyValueError::new_err(format!(
                "{name} must have shape ({m}, 3), got ({}, 3)",
                v.len()
            )));
        }
        if let Some(i) = v.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
            return Err(PyValueError::new_err(format!(
                "{name}: row {i} is not finite ({:?})",
                v[i]
            )));
        }
        Ok(self.order.to_internal(&v))
    }
}

/// Measure what synchronising `threads` threads costs on this machine (`sync_floor::SyncFloor`), in
/// about 0.1 s: (seconds per parallel region that every thread must join, with no work in it, back to back,
/// seconds per cache-line round trip between two threads; NaN on a single CPU).
#[pyfunction]
fn bench_sync_floor(py: Python<'_>, threads: usize) -> PyResult<(f64, f64)> {
    if threads == 0 {
        return Err(PyValueError::new_err("threads must be at least 1"));
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| PyRuntimeError::new_err(format!("cannot start {threads} threads: {e}")))?;
    let budget = std::time::Duration::from_millis(80);
    let floor = py.detach(|| pool.install(|| sync_floor::measure(budget)));
    Ok((floor.region_s, floor.round_trip_s))
}

/// Check a material dict (`settings::material`): raises ValueError naming the key as `material.key`.
#[pyfunction]
fn check_material(material: &Bound<'_, PyAny>) -> PyResult<()> {
    settings::material(material).map(|_| ())
}

/// Check an integrator dict (`settings::integrator`): raises ValueError naming the key as `integrator.key`.
#[pyfunction]
fn check_integrator(integrator: &Bound<'_, PyAny>) -> PyResult<()> {
    settings::integrator(integrator).map(|_| ())
}

/// Check a projection dict (`settings::projection`): raises ValueError naming the key as `projection.key`.
#[pyfunction]
fn check_projection(projection: &Bound<'_, PyAny>) -> PyResult<()> {
    settings::projection(projection).map(|_| ())
}

/// The material model the integrator named `integrator` fixes (its energy is the one the projection
/// conserves), or None (`fepr_core::simulation::conserved_material_name`).
#[pyfunction]
fn conserved_material(integrator: &str) -> Option<&'static str> {
    conserved_material_name(integrator)
}

/// The projection's warm-start threshold under `warm_start="auto"` after the integrator named `integrator`
/// (infinity: off; `fepr_core::simulation::auto_warm_start_threshold`).
#[pyfunction]
fn warm_start_threshold(integrator: &str) -> f64 {
    auto_warm_start_threshold(integrator)
}

/// Advance the bodies `sims` (same dt) `n` steps together, with contact between them
/// (`fepr_core::simulation::step_bodies`); `coefficients` holds each body's `(restitution, friction)`. On a
/// failure raises RuntimeError with args `(body index, message)`; the steps completed before it stay.
#[pyfunction]
#[pyo3(signature = (sims, n, coefficients, max_seconds=None))]
fn step_bodies(
    py: Python<'_>,
    mut sims: Vec<PyRefMut<'_, Simulation>>,
    n: usize,
    coefficients: Vec<(f64, f64)>,
    max_seconds: Option<f64>,
) -> PyResult<usize> {
    if sims.len() != coefficients.len() {
        return Err(PyValueError::new_err(format!(
            "{} bodies but {} coefficient pairs",
            sims.len(),
            coefficients.len()
        )));
    }
    let coeffs = coefficients
        .iter()
        .enumerate()
        .map(|(k, &(e, mu))| {
            BodyCoefficients::new(e, mu)
                .map_err(|err| PyValueError::new_err(format!("body {k}: {err}")))
        })
        .collect::<PyResult<Vec<_>>>()?;
    let Some(first) = sims.first() else {
        return Ok(0);
    };
    let dt = first.inner.dt();
    if let Some(k) = sims.iter().position(|s| s.inner.dt() != dt) {
        return Err(PyValueError::new_err(format!(
            "body {k} has dt = {} s, body 0 has {dt} s: bodies stepped together share one time step",
            sims[k].inner.dt()
        )));
    }
    let mut parts: Vec<(&mut CoreSimulation, &Threads)> = sims
        .iter_mut()
        .map(|s| {
            let s = &mut **s;
            (&mut s.inner, &s.threads)
        })
        .collect();
    let (inners, threads): (Vec<&mut CoreSimulation>, Vec<&Threads>) = parts.drain(..).unzip();
    let threads = threads[0];
    let mut inners = inners;
    let budget = max_seconds.unwrap_or(f64::INFINITY);
    let result = py.detach(|| {
        threads.run(|| -> Result<usize, (usize, FeprError)> {
            let t0 = std::time::Instant::now();
            for k in 0..n {
                fepr_core::simulation::step_bodies(&mut inners, &coeffs)?;
                if t0.elapsed().as_secs_f64() > budget {
                    return Ok(k + 1);
                }
            }
            Ok(n)
        })
    });
    result.map_err(|(k, e)| PyRuntimeError::new_err((k, e.to_string())))
}

/// Seconds per detection pass of contact between `sims` at their current states (nothing changes), the mean
/// over `repeats` (`fepr_core::simulation::time_body_detection`; for `fepr bench`).
#[pyfunction]
fn bench_body_detection(mut sims: Vec<PyRefMut<'_, Simulation>>, repeats: usize) -> PyResult<f64> {
    let mut inners: Vec<&mut CoreSimulation> = sims.iter_mut().map(|s| &mut s.inner).collect();
    fepr_core::simulation::time_body_detection(&mut inners, repeats).map_err(value_error)
}

/// Validate a triangle-mesh obstacle: `vertices` (n * 3, m) and `triangles` (k * 3 indices), flattened.
/// Returns whether it is closed; raises ValueError naming the vertex or triangle at fault.
#[pyfunction]
fn check_mesh_obstacle(vertices: Vec<f64>, triangles: Vec<u32>) -> PyResult<bool> {
    if !vertices.len().is_multiple_of(3) || !triangles.len().is_multiple_of(3) {
        return Err(PyValueError::new_err(
            "vertices and triangles must hold 3 entries per item",
        ));
    }
    let v: Vec<[f64; 3]> = vertices
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let t: Vec<[u32; 3]> = triangles
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    MeshCollider::new(&v, &t)
        .map(|m| m.is_closed())
        .map_err(|e| PyValueError::new_err(e.to_string()))
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(validate_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(obstacle_placement, m)?)?;
    m.add_function(wrap_pyfunction!(material_eval, m)?)?;
    m.add_function(wrap_pyfunction!(bench_sync_floor, m)?)?;
    m.add_class::<Simulation>()?;
    m.add_function(wrap_pyfunction!(check_material, m)?)?;
    m.add_function(wrap_pyfunction!(check_integrator, m)?)?;
    m.add_function(wrap_pyfunction!(check_projection, m)?)?;
    m.add_function(wrap_pyfunction!(conserved_material, m)?)?;
    m.add_function(wrap_pyfunction!(warm_start_threshold, m)?)?;
    m.add_function(wrap_pyfunction!(check_mesh_obstacle, m)?)?;
    m.add_function(wrap_pyfunction!(step_bodies, m)?)?;
    m.add_function(wrap_pyfunction!(bench_body_detection, m)?)?;
    // The name lists, each defined once in the core.
    m.add("INTEGRATORS", INTEGRATOR_NAMES.to_vec())?;
    m.add("MATERIALS", MATERIAL_NAMES.to_vec())?;
    m.add("PROJECTION_ROWS", ROW_NAMES.to_vec())?;
    m.add("METRICS", METRIC_NAMES.to_vec())?;
    m.add("PROJECTION_KEYS", settings::PROJECTION_KEYS.to_vec())?;
    m.add("SLACK_MODES", SLACK_NAMES.to_vec())?;
    m.add("WARM_START_MODES", WARM_START_MODES.to_vec())?;
    m.add("HISTORY_COLUMNS", HISTORY_COLUMNS.to_vec())?;
    m.add("HISTORY_INTEGER_COLUMNS", HISTORY_INTEGER_COLUMNS.to_vec())?;
    m.add("PROJECTION_REPORT_FIELDS", REPORT_FIELDS.to_vec())?;
    m.add("PD_WARM_START", PD_WARM_START)?;
    m.add("XPBD_WARM_START", XPBD_WARM_START)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}

//! Evaluating `c(q)`: the constraints, the elastic gradient and the mass moments that the small system
//! needs, and the D-norm distance from the base state. Every vertex sum runs over fixed tasks of vertices in
//! lanes, added in task order: the same bits for any thread count.

use super::problem::Problem;
use super::step::Step;
use super::ROWS;
use crate::elasticity::{elastic_gradient_chunks, ElasticSummary, ElasticWorkspace};
use crate::exec::{
    for_each_chunk_mut2, for_each_chunk_mut3, for_each_chunk_mut4, for_each_mut, reduce_chunks,
};
use crate::math::Vec3;
use crate::projection as tl;
use crate::projection::{self as ml, q, UPPER, VL};

/// Everything an evaluation of `c(q)` produces.
#[derive(Clone, Copy, Debug)]
pub(super) struct Eval {
    /// The moments for `S` (below) were summed; without them (a trial point, most of which end the
    /// projection) they are zero and must be summed before a solve.
    pub(super) s_moments: bool,
    pub(super) c: [f64; ROWS],
    pub(super) el: ElasticSummary,
    pub(super) kinetic: f64,
    pub(super) gravitational: f64,
    pub(super) momentum: Vec3,
    /// About the target centre of mass.
    pub(super) angular_momentum: Vec3,
    pub(super) com: Vec3,
    // Moments over the free vertices, for S. With the position metric `w_i = m_i / a_i` (`a_i = 1` for the
    // mass metric), the position-block moments carry the factor `a_i`; the velocity-block ones do not.
    pub(super) grad_sq_over_w: f64,
    pub(super) a_grad_sum: Vec3,
    pub(super) a_grad_cross_v: Vec3,
    pub(super) free_mass: f64,
    pub(super) a_free_mass: f64,
    pub(super) free_p: Vec3,
    pub(super) a_free_p: Vec3,
    pub(super) free_l: Vec3,
    pub(super) free_r: Vec3,
    pub(super) tr_vv: f64,
    pub(super) a_vv: [[f64; 3]; 3],
    pub(super) rr: [[f64; 3]; 3],
    // For the angular momentum's second-order term along a step (`angular_second_order`), with
    // `r_i = x_i - C_target`: `sum a_i g_i r_i^T`, `sum a_i m_i r_i x v_i`, `sum a_i m_i r_i`.
    pub(super) a_grad_r: [[f64; 3]; 3],
    pub(super) a_r_cross_v: Vec3,
    pub(super) a_mass_r: Vec3,
    /// `sum m_i x_i` (for the centre of mass).
    pub(super) mass_x: Vec3,
    /// The vertices' part of the squared D-norm distance from the base step's state, where the evaluation
    /// summed it (a trial point: [`Step::measured_from`]); the projection's correction is then known without
    /// a pass of its own when this point is the result.
    pub(super) correction_sq: Option<f64>,
}

impl Default for Eval {
    fn default() -> Self {
        let z = [0.0; 3];
        Self {
            s_moments: false,
            c: [0.0; ROWS],
            el: ElasticSummary {
                energy: 0.0,
                min_j: f64::INFINITY,
                inverted: 0,
            },
            kinetic: 0.0,
            gravitational: 0.0,
            momentum: z,
            angular_momentum: z,
            com: z,
            grad_sq_over_w: 0.0,
            a_grad_sum: z,
            a_grad_cross_v: z,
            free_mass: 0.0,
            a_free_mass: 0.0,
            free_p: z,
            a_free_p: z,
            free_l: z,
            free_r: z,
            tr_vv: 0.0,
            a_vv: [z; 3],
            rr: [z; 3],
            a_grad_r: [z; 3],
            a_r_cross_v: z,
            a_mass_r: z,
            mass_x: z,
            correction_sq: None,
        }
    }
}

impl Eval {
    /// Add the vertex sums of `b` (a later chunk) to these.
    pub(super) fn add(&mut self, b: &Eval) {
        self.s_moments &= b.s_moments;
        // In task order from the first task's value, as `d_norm` adds its task sums: the same bits.
        self.correction_sq = match (self.correction_sq, b.correction_sq) {
            (Some(a), Some(b)) => Some(a + b),
            _ => None,
        };
        let add3 = |a: &mut Vec3, b: &Vec3| (0..3).for_each(|k| a[k] += b[k]);
        self.kinetic += b.kinetic;
        self.gravitational += b.gravitational;
        self.grad_sq_over_w += b.grad_sq_over_w;
        self.free_mass += b.free_mass;
        self.a_free_mass += b.a_free_mass;
        self.tr_vv += b.tr_vv;
        add3(&mut self.momentum, &b.momentum);
        add3(&mut self.angular_momentum, &b.angular_momentum);
        add3(&mut self.a_grad_sum, &b.a_grad_sum);
        add3(&mut self.a_grad_cross_v, &b.a_grad_cross_v);
        add3(&mut self.free_p, &b.free_p);
        add3(&mut self.a_free_p, &b.a_free_p);
        add3(&mut self.free_l, &b.free_l);
        add3(&mut self.free_r, &b.free_r);
        add3(&mut self.mass_x, &b.mass_x);
        add3(&mut self.a_r_cross_v, &b.a_r_cross_v);
        add3(&mut self.a_mass_r, &b.a_mass_r);
        for a in 0..3 {
            add3(&mut self.a_vv[a], &b.a_vv[a]);
            add3(&mut self.rr[a], &b.rr[a]);
            add3(&mut self.a_grad_r[a], &b.a_grad_r[a]);
        }
    }
}

/// Scratch memory of an evaluation: the elastic pass's, and the vertex tasks' partial sums.
#[derive(Clone, Debug, Default)]
pub(super) struct EvalScratch {
    pub(super) ws: ElasticWorkspace,
    pub(super) parts: Vec<Eval>,
    /// The D-norm's per-task sums.
    pub(super) norms: Vec<f64>,
    /// The warm start's per-task kinetic energies.
    pub(super) kinetic: Vec<[f64; 3]>,
}

/// `|q - q_base|_D` with `D = diag(W, h^2 M, eps, eps)`, `W = diag(m_i / a_i)`.
#[allow(clippy::too_many_arguments)]
pub(super) fn d_norm(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    xb: &[Vec3],
    vb: &[Vec3],
    parts: &mut Vec<f64>,
) -> f64 {
    d_norm_from(pb, s, t, d_norm_vertex_sum(pb, x, v, xb, vb, parts))
}

/// The vertices' part of `|q - q_base|_D^2`.
pub(super) fn d_norm_vertex_sum(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    xb: &[Vec3],
    vb: &[Vec3],
    parts: &mut Vec<f64>,
) -> f64 {
    // Over fixed vertex tasks, each in lanes, added in task order (the same bits for any thread count, and
    // those of the trial pass's sums: `trial_lanes`).
    let map = |r: std::ops::Range<usize>| {
        let base = tl::BaseRows {
            x: &xb[r.clone()],
            v: &vb[r.clone()],
            h2: pb.h * pb.h,
        };
        let (mass, factor) = (&pb.model.masses[r.clone()], &pb.metric_factor[r.clone()]);
        ml::lane_sum(&tl::correction_lanes(
            &x[r.clone()],
            &v[r],
            base,
            mass,
            factor,
        ))
    };
    let sum = reduce_chunks(x.len(), vertex_chunk(x.len()), parts, map, |a, b| a + b);
    sum.unwrap_or(0.0)
}

/// `|q - q_base|_D` from the vertices' part of its square (the task sums of [`tl::correction_lanes`] added
/// in task order) and the slack values.
pub(super) fn d_norm_from(pb: &Problem, s: f64, t: f64, vertex_sum: f64) -> f64 {
    (pb.eps * (s * s + t * t) + vertex_sum).sqrt()
}

/// Evaluate the constraints, the elastic gradient (into `grad`; the potential's is `grad E_el - m g`, formed
/// where it is used) and the mass moments that `S` needs: the elastic pass's chunks, then one parallel pass
/// over fixed tasks of vertices that sums each vertex's gradient and the task's moments while they are in
/// cache (combined in task order: the same bits for any thread count).
pub(super) fn evaluate(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    sc: &mut EvalScratch,
    grad: &mut [Vec3],
) -> Eval {
    evaluate_sums::<true>(pb, x, v, s, t, sc, grad)
}

/// [`evaluate`], with the moments for `S` only if `S` (`Eval::s_moments`).
#[allow(clippy::too_many_arguments)]
pub(super) fn evaluate_sums<const S: bool>(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    sc: &mut EvalScratch,
    grad: &mut [Vec3],
) -> Eval {
    let el = elastic_gradient_chunks(pb.model, x, &mut sc.ws);
    let ws = &sc.ws;
    let chunk = vertex_chunk(grad.len());
    let parts = task_parts(&mut sc.parts, grad.len());
    for_each_chunk_mut2(grad, chunk, parts, 1, |c, g, part| {
        let first = c * chunk;
        for (k, gk) in g.iter_mut().enumerate() {
            *gk = ws.gradient_at(pb.model, first + k);
        }
        let r = first..first + g.len();
        part[0] = vertex_moments::<S>(pb, first, &x[r.clone()], &v[r], Some(g));
    });
    finish(pb, s, t, el, sum_parts(parts))
}

/// [`evaluate`] at the trial point of `step` (`q - alpha D^-1 G lambda`, written to `x_out`, `v_out`, its
/// elastic gradient to `g_out`), with the slack values `(s, t)` of that point; with the moments for `S` only
/// if `moments` (`Eval::s_moments`). The trial point is written by a pass of its own (computing each position
/// where the elastic chunks gather it is 1.5 times the work, and was slower). Without the moments, that pass
/// also sums the constraints and the D-norm distance as it writes each task's rows, while they are in
/// registers (a symplectic Euler step's only trial point).
#[allow(clippy::too_many_arguments)]
pub(super) fn evaluate_step(
    pb: &Problem,
    step: &Step,
    s: f64,
    t: f64,
    sc: &mut EvalScratch,
    (x_out, v_out, mirror): (&mut [Vec3], &mut [Vec3], Option<&mut [Vec3]>),
    g_out: &mut [Vec3],
    moments: bool,
) -> Eval {
    let chunk = vertex_chunk(x_out.len());
    if moments {
        // The D-norm distance is summed as the rows are written (the moment pass after the chunks sums the
        // rest).
        let norms = &mut sc.norms;
        norms.resize(x_out.len().div_ceil(chunk), 0.0);
        write_tasks(x_out, v_out, mirror, norms, chunk, |c, xo, vo, norm| {
            let sums = step.write(c * chunk, xo, vo, false);
            norm[0] = sums.correction.map_or(0.0, |lanes| ml::lane_sum(&lanes));
        });
        let correction_sq = step.base.map(|_| sum_in_order(&sc.norms));
        let mut e = evaluate_sums::<true>(pb, x_out, v_out, s, t, sc, g_out);
        e.correction_sq = correction_sq;
        return e;
    }
    // Without the moments for `S`, every vertex sum of the trial point (the constraints' and its D-norm
    // distance from q~) needs its rows alone: each task sums them as it writes them, while they are in
    // registers, and the pass after the elastic chunks only gathers the gradient. The same lanes and the same
    // tasks as the moment pass's sums, so the same bits (`the_trial_pass_sums_what_an_evaluation_sums`).
    let parts = task_parts(&mut sc.parts, x_out.len());
    write_tasks(
        x_out,
        v_out,
        mirror,
        &mut parts[..],
        chunk,
        |c, xo, vo, part| {
            let sums = step.write(c * chunk, xo, vo, true);
            let constraints = sums.constraints.expect("asked for");
            part[0] = Eval {
                correction_sq: sums.correction.map(|lanes| ml::lane_sum(&lanes)),
                ..constraint_sums(&constraints)
            };
        },
    );
    let el = elastic_gradient_chunks(pb.model, x_out, &mut sc.ws);
    sc.ws.gradient_into(pb.model, g_out);
    finish(pb, s, t, el, sum_parts(parts))
}

/// `write(c, x_rows, v_rows, part)` over the vertex tasks of `chunk` rows (task `c`'s rows of `x_out` and
/// `v_out`, and `parts[c]`), in parallel; with `mirror` (as long as `x_out`), each task then copies the
/// positions it wrote into the mirror's rows, while they are in L1 (see [`Mirror`]).
pub(super) fn write_tasks<P: Send>(
    x_out: &mut [Vec3],
    v_out: &mut [Vec3],
    mirror: Option<&mut [Vec3]>,
    parts: &mut [P],
    chunk: usize,
    write: impl Fn(usize, &mut [Vec3], &mut [Vec3], &mut [P]) + Sync,
) {
    match mirror {
        None => for_each_chunk_mut3(x_out, chunk, v_out, chunk, parts, 1, write),
        Some(mirror) => for_each_chunk_mut4(
            x_out,
            chunk,
            v_out,
            chunk,
            mirror,
            chunk,
            parts,
            1,
            |c, xo, vo, mo, part| {
                write(c, xo, vo, part);
                mo.copy_from_slice(xo);
            },
        ),
    }
}

/// Per-task sums added in task order.
pub(super) fn sum_in_order(parts: &[f64]) -> f64 {
    parts.iter().copied().reduce(|a, b| a + b).unwrap_or(0.0)
}

/// [`evaluate`] without the elastic gradient: the same constraint values, energies and momenta; the gradient
/// moments of `S` are left at zero (not to be solved with).
pub(super) fn evaluate_energy(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    parts: &mut Vec<Eval>,
) -> Eval {
    let el = crate::elasticity::elastic_energy(pb.model, x);
    evaluate_with_elastic(pb, x, v, s, t, el, None, parts)
}

/// [`evaluate`] with the elastic energy summary `el` (and gradient `grad`) at `x` already at hand (after a
/// change of the velocities alone; or the energy alone): the same result, without the elastic pass. Without
/// `grad`, the moments that need it are left at zero (not to be solved with).
#[allow(clippy::too_many_arguments)]
pub(super) fn evaluate_with_elastic(
    pb: &Problem,
    x: &[Vec3],
    v: &[Vec3],
    s: f64,
    t: f64,
    el: ElasticSummary,
    grad: Option<&[Vec3]>,
    parts: &mut Vec<Eval>,
) -> Eval {
    let chunk = vertex_chunk(x.len());
    let parts = task_parts(parts, x.len());
    for_each_mut(parts, |c, part| {
        let first = c * chunk;
        let r = first..(first + chunk).min(x.len());
        let g = grad.map(|g| &g[r.clone()]);
        *part = vertex_moments::<true>(pb, first, &x[r.clone()], &v[r], g);
    });
    finish(pb, s, t, el, sum_parts(parts))
}

/// `parts` resized to one entry per vertex task of `m` vertices (no allocation once grown).
pub(super) fn task_parts(parts: &mut Vec<Eval>, m: usize) -> &mut [Eval] {
    parts.resize(m.div_ceil(vertex_chunk(m)), Eval::default());
    &mut parts[..]
}

/// The vertex tasks' sums, added in task order.
pub(super) fn sum_parts(parts: &[Eval]) -> Eval {
    match parts.split_first() {
        None => Eval::default(),
        Some((first, rest)) => rest.iter().fold(*first, |mut a, b| {
            a.add(b);
            a
        }),
    }
}

/// The constraint values of the vertex sums `e` with the elastic summary `el`, at slack values `(s, t)`.
pub(super) fn finish(pb: &Problem, s: f64, t: f64, el: ElasticSummary, mut e: Eval) -> Eval {
    let mt = pb.model.total_mass;
    e.el = el;
    e.com = [e.mass_x[0] / mt, e.mass_x[1] / mt, e.mass_x[2] / mt];
    let tg = pb.targets;
    e.c[0] = e.kinetic + el.energy + e.gravitational - tg.energy;
    for a in 0..3 {
        e.c[1 + a] = e.momentum[a] - (tg.momentum[a] + s * pb.dp_star[a]);
        e.c[4 + a] = e.angular_momentum[a] - (tg.angular_momentum[a] + t * pb.dl_star[a]);
        e.c[7 + a] = e.com[a] - tg.center_of_mass[a];
    }
    e
}

/// Vertices per parallel task of the moment pass, the trial step and the D-norm: the length of every vertex
/// pass ([`crate::exec::vertex_task_len`]), a multiple of the moment lanes.
pub(super) fn vertex_chunk(m: usize) -> usize {
    const { assert!(VL == 4, "vertex_task_len is a multiple of 4") };
    crate::exec::vertex_task_len(m)
}

/// The sums of [`Eval`] over the vertices `first..first + x.len()` (`x`, `v`, `grad`: their rows; `c`, `el`
/// and `com` are left at zero), in the fixed lane order of [`crate::projection`] (the same bits for any
/// thread count). With `S`, the constraints' sums and the moments for `S`; the second-order ones only with
/// a gradient. Without a gradient the moments take the elastic gradient as zero: the velocity moments (the
/// warm start's) are exact, the others are not to be solved with (an iteration evaluates the gradient first).
/// Without `S`, the constraints' sums alone.
pub(super) fn vertex_moments<const S: bool>(
    pb: &Problem,
    first: usize,
    x: &[Vec3],
    v: &[Vec3],
    grad: Option<&[Vec3]>,
) -> Eval {
    let model = pb.model;
    let (g, ct) = (model.gravity, pb.targets.center_of_mass);
    let r = first..first + x.len();
    let mass = &model.masses[r.clone()];
    if !S {
        return constraint_sums(&ml::constraint_lanes(x, v, mass, g, ct));
    }
    let rows = ml::Rows {
        x,
        v,
        grad,
        mass,
        free_mass: &pb.rows.free_mass[r.clone()],
        free_factor: &pb.rows.free_factor[r],
        unit: pb.rows.unit,
    };
    // The second-order moments only with a gradient (a solve needs them; the energy-only first evaluation
    // and the warm start, which mostly end the projection after Projective Dynamics, do not).
    let (acc, second) = match grad {
        Some(_) => ml::moment_and_second_order_lanes(&rows, g, ct),
        None => (
            ml::moment_lanes(&rows, g, ct),
            [[0.0; VL]; ml::SECOND_ORDER_SUMS],
        ),
    };
    let sum = |k: usize| ml::lane_sum(&acc[k]);
    let vec3 = |k: usize| [sum(k), sum(k + 1), sum(k + 2)];
    let sym = |k: usize| {
        let mut s = [[0.0; 3]; 3];
        for (j, &(a, b)) in UPPER.iter().enumerate() {
            s[a][b] = sum(k + j);
            s[b][a] = s[a][b];
        }
        s
    };
    let sum2 = |k: usize| ml::lane_sum(&second[k]);
    Eval {
        s_moments: true,
        kinetic: sum(q::KINETIC),
        gravitational: sum(q::GRAVITATIONAL),
        momentum: vec3(q::MOMENTUM),
        angular_momentum: vec3(q::ANGULAR),
        mass_x: vec3(q::MASS_X),
        free_mass: sum(q::FREE_MASS),
        a_free_mass: sum(q::A_FREE_MASS),
        grad_sq_over_w: sum(q::GRAD_SQ_OVER_W),
        tr_vv: sum(q::TR_VV),
        a_grad_sum: vec3(q::A_GRAD_SUM),
        a_grad_cross_v: vec3(q::A_GRAD_CROSS_V),
        free_p: vec3(q::FREE_P),
        a_free_p: vec3(q::A_FREE_P),
        free_l: vec3(q::FREE_L),
        free_r: vec3(q::FREE_R),
        a_vv: sym(q::A_VV),
        rr: sym(q::RR),
        a_grad_r: std::array::from_fn(|c| [sum2(3 * c), sum2(3 * c + 1), sum2(3 * c + 2)]),
        a_r_cross_v: [sum2(9), sum2(10), sum2(11)],
        a_mass_r: [sum2(12), sum2(13), sum2(14)],
        ..Eval::default()
    }
}

/// The constraints' sums of a task from their lanes ([`ml::constraint_lanes`]), without the moments for `S`.
pub(super) fn constraint_sums(acc: &[ml::Lane; ml::CONSTRAINT_SUMS]) -> Eval {
    let sum = |k: usize| ml::lane_sum(&acc[k]);
    let vec3 = |k: usize| [sum(k), sum(k + 1), sum(k + 2)];
    Eval {
        s_moments: false,
        kinetic: sum(q::KINETIC),
        gravitational: sum(q::GRAVITATIONAL),
        momentum: vec3(q::MOMENTUM),
        angular_momentum: vec3(q::ANGULAR),
        mass_x: vec3(q::MASS_X),
        ..Eval::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::{Material, NeoHookean};
    use crate::math::Vec3;
    use crate::projection::problem::MetricRows;
    use crate::projection::test_support::*;
    use crate::projection::{ProjectionSettings, Projector, ROWS};

    /// The trial evaluation sums its point's D-norm distance from the base state in the same task order as
    /// `d_norm`'s own pass: the projection's reported correction (taken from it when the result is a trial
    /// point) keeps its bits, for the mass and the stiffness metric and with a pinned vertex.
    #[test]
    fn the_correction_summed_by_the_trial_pass_is_the_d_norm_pass_bit_for_bit() {
        for (implicit, pin) in [(false, false), (true, false), (false, true)] {
            let mut model = cube_model(1e4, [0.0, 0.0, -9.81]);
            model.pinned[2] = pin;
            let (state, targets) = stretched_and_moving(&model);
            let h = 0.005;
            let mut proj = Projector::new(ProjectionSettings::default()).unwrap();
            proj.set_implicit_base(implicit);
            let mut out = state.clone();
            let (report, _) = proj.project(&model, &mut out, h, &targets);
            assert!(report.converged && report.iterations >= 1, "{report:?}");
            assert!(
                !report.warm_start,
                "the result is a trial point: {report:?}"
            );
            let eps = proj.settings.c_eps * model.total_mass * model.length_scale.powi(2);
            let (factors, rows) = (proj.metric_factor.clone(), MetricRows::default());
            let pb = Problem::new(&model, h, &targets, factors, rows, [true; ROWS], eps)
                .with_fresh_rows();
            let pass = d_norm(
                &pb,
                &out.x,
                &out.v,
                report.s,
                report.t,
                &proj.x_base,
                &proj.v_base,
                &mut Vec::new(),
            );
            assert!(report.correction > 0.0);
            assert_eq!(report.correction.to_bits(), pass.to_bits(), "{report:?}");

            // The trial evaluation's sum itself (so that the gate above cannot pass by both sides taking the
            // pass): a step from the base state, measured from it, against the pass's vertex sum.
            let m = model.num_vertices();
            let (xb, vb) = (proj.x_base.clone(), proj.v_base.clone());
            let mut grad = vec![[0.0; 3]; m];
            let mut sc = EvalScratch::default();
            evaluate(&pb, &xb, &vb, 0.0, 0.0, &mut sc, &mut grad);
            let lambda = [0.3, -0.2, 0.1, 0.05, 0.02, -0.04, 0.03, 0.2, -0.1, 0.07];
            let step = Step::new(&pb, &xb, &vb, &grad, &lambda, 0.5).measured_from(&xb, &vb);
            let (mut xo, mut vo, mut go) =
                (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
            let e = evaluate_step(
                &pb,
                &step,
                0.0,
                0.0,
                &mut sc,
                (&mut xo, &mut vo, None),
                &mut go,
                false,
            );
            let want = d_norm(&pb, &xo, &vo, 0.0, 0.0, &xb, &vb, &mut Vec::new());
            let got = d_norm_from(
                &pb,
                0.0,
                0.0,
                e.correction_sq.expect("summed by the trial pass"),
            );
            assert!(want > 0.0);
            assert_eq!(got.to_bits(), want.to_bits());
        }
    }

    /// A trial point without the moments for `S` has its vertex sums taken as each task writes its rows: every
    /// constraint sum, the D-norm sum, the elastic summary and the gradient keep the bits of `evaluate_sums`,
    /// which sums them after the elastic chunks (as trial points with the moments still do), over several
    /// vertex tasks and any thread count. Fails if the written rows are summed in another order or over other
    /// tasks.
    #[test]
    fn the_trial_pass_sums_what_an_evaluation_sums() {
        let model = crate::elasticity::tests::grid_model(
            6,
            Material::NeoHookean(NeoHookean::new(1e4, 0.3).unwrap()),
        );
        let m = model.num_vertices();
        assert!(m >= 4 * vertex_chunk(m), "several vertex tasks: {m}");
        let (state, targets) = stretched_and_moving(&model);
        let (x, v) = (&state.x, &state.v);
        let h = 0.005;
        let eps = 1e-6 * model.total_mass * model.length_scale.powi(2);
        let pb = Problem::new(
            &model,
            h,
            &targets,
            vec![1.0; m],
            MetricRows::default(),
            [true; ROWS],
            eps,
        )
        .with_fresh_rows();
        let mut grad = vec![[0.0; 3]; m];
        evaluate(&pb, x, v, 0.0, 0.0, &mut EvalScratch::default(), &mut grad);
        let lambda = [0.3, -0.2, 0.1, 0.05, 0.02, -0.04, 0.03, 0.2, -0.1, 0.07];
        let step = Step::new(&pb, x, v, &grad, &lambda, 0.7).measured_from(x, v);
        // The reference: the rows written, then summed by the evaluation's own pass after the chunks.
        let (mut xr, mut vr, mut gr) = (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
        step.write(0, &mut xr, &mut vr, false);
        let mut sc = EvalScratch::default();
        let mut want = evaluate_sums::<false>(&pb, &xr, &vr, 0.1, 0.2, &mut sc, &mut gr);
        let norms = &mut Vec::new();
        want.correction_sq = Some(d_norm_vertex_sum(&pb, &xr, &vr, x, v, norms));
        let sums = |e: &Eval| {
            let mut b = vec![e.kinetic, e.gravitational, e.el.energy, e.el.min_j];
            b.extend(e.c);
            b.extend(
                e.momentum
                    .iter()
                    .chain(&e.angular_momentum)
                    .chain(&e.mass_x),
            );
            b.push(e.correction_sq.expect("the trial's D-norm sum"));
            b.into_iter().map(f64::to_bits).collect::<Vec<_>>()
        };
        let rows = |a: &[Vec3]| a.iter().flatten().map(|c| c.to_bits()).collect::<Vec<_>>();
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let (e, xo, go) = pool.install(|| {
                let (mut xo, mut vo, mut go) =
                    (vec![[0.0; 3]; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
                let mut sc = EvalScratch::default();
                let e = evaluate_step(
                    &pb,
                    &step,
                    0.1,
                    0.2,
                    &mut sc,
                    (&mut xo, &mut vo, None),
                    &mut go,
                    false,
                );
                (e, xo, go)
            });
            assert!(!e.s_moments);
            assert_eq!(sums(&e), sums(&want), "{threads} threads");
            assert_eq!(rows(&xo), rows(&xr), "{threads} threads");
            assert_eq!(rows(&go), rows(&gr), "{threads} threads");
        }
    }
}

//! XPBD (Macklin, Mueller, Chentanez 2016) with the Neo-Hookean constraints of Macklin and Mueller 2021: per
//! tet a deviatoric constraint `C_D = sqrt(I_C)` with compliance `1 / (mu V)` and a hydrostatic constraint
//! `C_H = J - alpha` with compliance `1 / (lambda' V)`. Their energies `C^2 / (2 compliance)` sum to the
//! [`ConstraintNeoHookean`] energy (up to a constant), which is therefore the `U` in FEPR's H (fepr-spec
//! section 5).
//!
//! A step of size `h` runs `substeps` substeps of size `h_s = h / substeps`; each predicts
//! `x = x_n + h_s v + h_s^2 g`, resets the multipliers, runs `iterations` Gauss-Seidel sweeps over the
//! constraints, and sets `v = (x - x_n) / h_s`. The sweeps go colour by colour (a greedy colouring in which the
//! tets of one colour share no vertex): within a colour the tets are solved in parallel, which is exactly the
//! sequential Gauss-Seidel result, so the step is bit-identical for any number of threads.

use rayon::prelude::*;

use crate::error::{invalid, Result};
use crate::hessian::shape_gradients;
use crate::integrators::{Integrator, StepReport};
use crate::linalg::{cofactor, det, scale, Mat3, Vec3};
use crate::material::{ConstraintNeoHookean, Material};
use crate::model::{Model, State};

/// XPBD settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct XpbdSettings {
    /// Substeps per step (default 20).
    pub substeps: usize,
    /// Gauss-Seidel sweeps per substep (default 1).
    pub iterations: usize,
}

impl Default for XpbdSettings {
    fn default() -> Self {
        // "Small steps" (Macklin et al. 2019): substeps with one sweep each. XPBD's local solves drop the
        // constraints' curvature (the deviatoric constraint sqrt(I_C) is pre-stressed at rest), which large
        // substeps on stiff elements turn into a divergent Gauss-Seidel sweep; small substeps keep the mass term
        // dominant.
        Self {
            substeps: 20,
            iterations: 1,
        }
    }
}

/// Per-run data: the colouring and the per-tet constants.
struct Prepared {
    /// Tets of each colour, in tet order.
    colours: Vec<Vec<usize>>,
    grads: Vec<[Vec3; 4]>,
    /// Compliances `1 / (mu V)` and `1 / (lambda' V)` per tet.
    compliance: Vec<[f64; 2]>,
    inv_mass: Vec<f64>,
}

/// The XPBD integrator.
#[derive(Default)]
pub struct Xpbd {
    pub settings: XpbdSettings,
    pre: Option<Prepared>,
    lambdas: Vec<[f64; 2]>,
    /// Per tet of the current colour: corner displacements and new multipliers.
    updates: Vec<([Vec3; 4], [f64; 2])>,
    /// Positions at the start of the substep (reused, no allocation per step).
    x_prev: Vec<Vec3>,
}

impl std::fmt::Debug for Xpbd {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Xpbd")
            .field("settings", &self.settings)
            .finish()
    }
}

/// Greedy colouring of the tets: no two tets that share a vertex get the same colour. Deterministic (tets in
/// index order, smallest free colour).
pub fn colour_tets(model: &Model) -> Vec<Vec<usize>> {
    let tets = model.mesh.tets();
    let mut colour = vec![usize::MAX; tets.len()];
    // forbidden[c] == e + 1: colour c is used by a neighbour of tet e.
    let mut forbidden: Vec<usize> = Vec::new();
    let offsets = &model.incidence_offsets;
    let slots = &model.incidence_slots;
    let mut colours: Vec<Vec<usize>> = Vec::new();
    for (e, t) in tets.iter().enumerate() {
        for &v in t {
            for &slot in &slots[offsets[v]..offsets[v + 1]] {
                let f = slot as usize / 4;
                if colour[f] != usize::MAX {
                    forbidden[colour[f]] = e + 1;
                }
            }
        }
        let c = (0..forbidden.len())
            .find(|&c| forbidden[c] != e + 1)
            .unwrap_or(forbidden.len());
        if c == forbidden.len() {
            forbidden.push(0);
            colours.push(Vec::new());
        }
        colour[e] = c;
        colours[c].push(e);
    }
    colours
}

impl Xpbd {
    pub fn new(settings: XpbdSettings) -> Result<Self> {
        if settings.substeps == 0 || settings.substeps > 10_000 {
            return Err(invalid(
                "xpbd_substeps",
                format!("must be in 1..=10000, got {}", settings.substeps),
            ));
        }
        if settings.iterations == 0 || settings.iterations > 10_000 {
            return Err(invalid(
                "xpbd_iterations",
                format!("must be in 1..=10000, got {}", settings.iterations),
            ));
        }
        Ok(Self {
            settings,
            ..Default::default()
        })
    }

    fn material(model: &Model) -> Option<ConstraintNeoHookean> {
        match model.material {
            Material::ConstraintNeoHookean(c) => Some(c),
            _ => None,
        }
    }

    fn prepare(model: &Model, mat: ConstraintNeoHookean) -> Prepared {
        let grads = (0..model.num_tets())
            .map(|e| shape_gradients(model, e))
            .collect();
        let compliance = model
            .rest
            .volume
            .iter()
            .map(|v| [1.0 / (mat.mu * v), 1.0 / (mat.lambda * v)])
            .collect();
        let inv_mass = (0..model.num_vertices())
            .map(|i| {
                if model.pinned[i] || model.masses[i] <= 0.0 {
                    0.0
                } else {
                    1.0 / model.masses[i]
                }
            })
            .collect();
        Prepared {
            colours: colour_tets(model),
            grads,
            compliance,
            inv_mass,
        }
    }
}

/// `F = sum_k x_k g_k^T` of a tet from its four corner positions.
fn deformation(p: &[Vec3; 4], g: &[Vec3; 4]) -> Mat3 {
    let mut f = [[0.0; 3]; 3];
    for k in 0..4 {
        for a in 0..3 {
            for b in 0..3 {
                f[a][b] += p[k][a] * g[k][b];
            }
        }
    }
    f
}

/// One coupled XPBD update of a tet's two constraints (a 2x2 block solve of the linearised conditions
/// `C_c + alpha~_c lambda_c + grad C_c . dx = 0`, `dx = W (grad C_D dl_D + grad C_H dl_H)`). Solving them together
/// matters: at rest their gradients are parallel (both a pure dilation) and their forces cancel, which a
/// sequential (one-then-the-other) update misses, collapsing and re-inflating stiff elements.
fn project_tet(
    p: &mut [Vec3; 4],
    w: &[f64; 4],
    g: &[Vec3; 4],
    alpha: f64,
    alpha_tilde: [f64; 2],
    lambda: &mut [f64; 2],
) {
    let f = deformation(p, g);
    let norm = crate::linalg::ddot(&f, &f).sqrt();
    // C_D = |F|, dC_D/dF = F / |F| (undefined at F = 0: a collapsed tet is left to the hydrostatic term).
    let (c_d, q_d) = if norm > 1e-12 {
        (norm, f.map(|row| row.map(|v| v / norm)))
    } else {
        (0.0, [[0.0; 3]; 3])
    };
    // C_H = J - alpha, dC_H/dF = cof F.
    let c_h = det(&f) - alpha;
    let q_h = cofactor(&f);
    let mut gd = [[0.0; 3]; 4];
    let mut gh = [[0.0; 3]; 4];
    let (mut a11, mut a12, mut a22) = (alpha_tilde[0], 0.0, alpha_tilde[1]);
    for k in 0..4 {
        for a in 0..3 {
            gd[k][a] = q_d[a][0] * g[k][0] + q_d[a][1] * g[k][1] + q_d[a][2] * g[k][2];
            gh[k][a] = q_h[a][0] * g[k][0] + q_h[a][1] * g[k][1] + q_h[a][2] * g[k][2];
        }
        a11 += w[k] * crate::linalg::dot(gd[k], gd[k]);
        a12 += w[k] * crate::linalg::dot(gd[k], gh[k]);
        a22 += w[k] * crate::linalg::dot(gh[k], gh[k]);
    }
    let b1 = -c_d - alpha_tilde[0] * lambda[0];
    let b2 = -c_h - alpha_tilde[1] * lambda[1];
    let det2 = a11 * a22 - a12 * a12;
    if !(det2 > 0.0 && det2.is_finite()) {
        return;
    }
    let dl_d = (a22 * b1 - a12 * b2) / det2;
    let dl_h = (a11 * b2 - a12 * b1) / det2;
    lambda[0] += dl_d;
    lambda[1] += dl_h;
    for k in 0..4 {
        for a in 0..3 {
            p[k][a] += w[k] * (gd[k][a] * dl_d + gh[k][a] * dl_h);
        }
    }
}

impl Integrator for Xpbd {
    fn name(&self) -> &'static str {
        "xpbd"
    }

    fn is_implicit(&self) -> bool {
        true
    }

    fn check(&self, model: &Model) -> Result<()> {
        match Self::material(model) {
            Some(_) => Ok(()),
            None => Err(invalid(
                "material",
                "xpbd solves the Neo-Hookean constraints of Macklin and Mueller 2021; give the ConstraintNeoHookean \
                 material so that FEPR conserves the energy its compliance encodes",
            )),
        }
    }

    fn step(&mut self, model: &Model, state: &mut State, h: f64) -> StepReport {
        let Some(mat) = Self::material(model) else {
            // Only reachable without `check`: poison the state so that the simulation reports it.
            state.x.iter_mut().for_each(|p| *p = [f64::NAN; 3]);
            return StepReport::default();
        };
        if self.pre.is_none() {
            self.pre = Some(Self::prepare(model, mat));
        }
        let pre = self.pre.as_ref().expect("prepared");
        let m = model.num_vertices();
        let hs = h / self.settings.substeps as f64;
        let inv_hs2 = 1.0 / (hs * hs);
        let g = model.gravity;
        let tets = model.mesh.tets();
        self.lambdas.resize(model.num_tets(), [0.0; 2]);
        let mut x_prev = std::mem::take(&mut self.x_prev);
        x_prev.resize(m, [0.0; 3]);
        for _ in 0..self.settings.substeps {
            x_prev.copy_from_slice(&state.x);
            for i in 0..m {
                if model.pinned[i] {
                    state.v[i] = [0.0; 3];
                    continue;
                }
                for a in 0..3 {
                    state.v[i][a] += hs * g[a];
                    state.x[i][a] += hs * state.v[i][a];
                }
            }
            self.lambdas.iter_mut().for_each(|l| *l = [0.0; 2]);
            for _ in 0..self.settings.iterations {
                for colour in &pre.colours {
                    let x = &state.x;
                    // Tets of one colour share no vertex: solve them in parallel from the same positions, then
                    // apply; identical to a sequential sweep over the colour.
                    let lambdas = &self.lambdas;
                    self.updates.resize(colour.len(), ([[0.0; 3]; 4], [0.0; 2]));
                    self.updates
                        .par_iter_mut()
                        .zip(colour.par_iter())
                        .for_each(|(out, &e)| {
                            let t = &tets[e];
                            let p0 = [x[t[0]], x[t[1]], x[t[2]], x[t[3]]];
                            let mut p = p0;
                            let w = t.map(|v| pre.inv_mass[v]);
                            let gr = &pre.grads[e];
                            let mut lam = lambdas[e];
                            project_tet(
                                &mut p,
                                &w,
                                gr,
                                mat.alpha,
                                [
                                    pre.compliance[e][0] * inv_hs2,
                                    pre.compliance[e][1] * inv_hs2,
                                ],
                                &mut lam,
                            );
                            let d = [0, 1, 2, 3].map(|k| {
                                [p[k][0] - p0[k][0], p[k][1] - p0[k][1], p[k][2] - p0[k][2]]
                            });
                            *out = (d, lam);
                        });
                    for (&e, (d, lam)) in colour.iter().zip(&self.updates) {
                        self.lambdas[e] = *lam;
                        for (k, &v) in tets[e].iter().enumerate() {
                            for a in 0..3 {
                                state.x[v][a] += d[k][a];
                            }
                        }
                    }
                }
            }
            let inv_hs = 1.0 / hs;
            for i in 0..m {
                if model.pinned[i] {
                    state.x[i] = x_prev[i];
                    state.v[i] = [0.0; 3];
                    continue;
                }
                for a in 0..3 {
                    state.v[i][a] = (state.x[i][a] - x_prev[i][a]) * inv_hs;
                }
            }
        }
        self.x_prev = x_prev;
        state.time += h;
        StepReport {
            impulse: scale(g, h * model.free_mass()),
            iterations: self.settings.iterations * self.settings.substeps,
            ..Default::default()
        }
    }
}

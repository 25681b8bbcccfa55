//! A cheap, conservative bound on how far a projection moved any tet's volume ratio, so that the quality guard
//! skips its per-tet check where the correction is far too small to matter (every step of a symplectic Euler
//! run, most steps of a resolved motion).
//!
//! The guard's full check reads every tet's corners in four states and takes four determinants. The bound reads
//! each vertex once and is O(1) after that:
//!
//! - the projection's largest change of a vertex, `d = max_i max(|x_i - x*_i|, |x_i + h v_i - x*_i - h v*_i|)`;
//! - how far the base step's state drifted from the state `x^` of the last full check, the whole body's
//!   translation removed: `a = max_i |x*_i - x^_i - (c* - c^)| + h |v*_i - V*|` (`c`: centre of mass, `V*`: mean
//!   velocity);
//! - the tets' sensitivities at that full check, `S_k = max_e L_e^k / (6 V_e)` (k = 0, 1, 2), with `L_e` the
//!   longest of tet `e`'s edges from its corner 0.
//!
//! A tet's edges in the base state (now, or one step ahead) are then at most `E = L_e + 2a` long, and the
//! projection changes each by at most `e = 2d`; the determinant is multilinear in the edges, so
//! `|J - J*| <= (3 e E^2 + 3 e^2 E + e^3) / (6 V_e) <= 3e (S_2 + 4a S_1 + 4a^2 S_0) + 3e^2 (S_1 + 2a S_0) + e^3 S_0`.
//! Where that is within the guard's margin (and below the base state's smallest volume ratio, so no tet can
//! flip), the per-tet trust region holds and the full check is not needed.

use crate::checkpoint::Carry;
use crate::error::Result;
use crate::exec::{copy_rows, reduce_chunks};
use crate::invariants::{center_of_mass, linear_momentum};
use crate::math::{norm, sub, Vec3};
use crate::model::{Model, ModelKey, State};

/// Vertices per task of the bound's pass.
const VERTICES_PER_TASK: usize = 4096;

/// The tets' sensitivities of a full check: `max_e L_e^k / (6 V_e)` for k = 0, 1, 2 (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Sensitivity(pub [f64; 3]);

impl Sensitivity {
    /// One tet's: `longest`, its longest edge from corner 0 (m), `inv`, `1 / (6 V_rest)`.
    #[inline]
    pub(super) fn of_tet(longest: f64, inv: f64) -> Self {
        Self([inv, longest * inv, longest * longest * inv])
    }
    pub(super) fn max(a: Self, b: Self) -> Self {
        Self(std::array::from_fn(|k| a.0[k].max(b.0[k])))
    }
}

/// The state of the last full check, and the bound's scratch.
#[derive(Clone, Debug, Default)]
pub(super) struct Certificate {
    /// The model the kept sensitivity belongs to ([`Model::elastic_key`]); `None`: nothing kept.
    key: Option<ModelKey>,
    /// Positions of the last full check's base state and its centre of mass.
    x_hat: Vec<Vec3>,
    c_hat: Vec3,
    sensitivity: Sensitivity,
    parts: Vec<[f64; 2]>,
}

impl Certificate {
    /// Keep the base state `x` of a full check and its tets' sensitivity.
    pub(super) fn keep(&mut self, model: &Model, x: &[Vec3], sensitivity: Sensitivity) {
        copy_rows(x, &mut self.x_hat);
        self.c_hat = center_of_mass(&model.masses, model.total_mass, x);
        self.sensitivity = sensitivity;
        self.key = Some(model.elastic_key());
    }

    /// What the next steps' bounds start from, into a checkpoint (`prefix` names its entries): the last full
    /// check's base positions, centre of mass and sensitivity (empty where nothing is kept).
    pub(super) fn carry(&self, model: &Model, prefix: &str, c: &mut Carry) {
        let kept =
            self.key == Some(model.elastic_key()) && self.x_hat.len() == model.num_vertices();
        let (x, rest): (&[Vec3], Vec<f64>) = if kept {
            let mut rest = self.c_hat.to_vec();
            rest.extend_from_slice(&self.sensitivity.0);
            (&self.x_hat, rest)
        } else {
            (&[], Vec::new())
        };
        c.put_vec3s(&format!("{prefix}.x"), x);
        c.put(&format!("{prefix}.center_sensitivity"), rest);
    }

    /// Back from [`Certificate::carry`].
    pub(super) fn resume(&mut self, model: &Model, prefix: &str, c: &Carry) -> Result<()> {
        let rest = c.get(&format!("{prefix}.center_sensitivity"))?;
        if rest.is_empty() {
            *self = Self::default();
            return Ok(());
        }
        let rest = c.get_len(&format!("{prefix}.center_sensitivity"), 6)?;
        self.x_hat = c.vec3s(&format!("{prefix}.x"), model.num_vertices())?;
        self.c_hat = [rest[0], rest[1], rest[2]];
        self.sensitivity = Sensitivity([rest[3], rest[4], rest[5]]);
        self.key = Some(model.elastic_key());
        Ok(())
    }

    /// The largest change of a tet's volume ratio that the projection from `(xb, vb)` to `state` can have
    /// made (now or one step ahead of `h`), or `None` where nothing is kept for `model`.
    pub(super) fn bound(
        &mut self,
        model: &Model,
        h: f64,
        (xb, vb): (&[Vec3], &[Vec3]),
        state: &State,
    ) -> Option<f64> {
        let m = model.num_vertices();
        if self.key != Some(model.elastic_key()) || self.x_hat.len() != m {
            return None;
        }
        let shift = sub(
            center_of_mass(&model.masses, model.total_mass, xb),
            self.c_hat,
        );
        let mean_v = linear_momentum(&model.masses, vb).map(|p| p / model.total_mass);
        let (x, v, x_hat) = (&state.x[..], &state.v[..], &self.x_hat[..]);
        let map = |r: std::ops::Range<usize>| {
            let (mut a, mut d) = (0.0_f64, 0.0_f64);
            for i in r {
                let moved = std::array::from_fn(|k| xb[i][k] - x_hat[i][k] - shift[k]);
                a = a.max(norm(moved) + h * norm(sub(vb[i], mean_v)));
                let dx = sub(x[i], xb[i]);
                let ahead = std::array::from_fn(|k| dx[k] + h * (v[i][k] - vb[i][k]));
                d = d.max(norm(dx).max(norm(ahead)));
            }
            [a, d]
        };
        let [a, d] = reduce_chunks(m, VERTICES_PER_TASK, &mut self.parts, map, |p, q| {
            [p[0].max(q[0]), p[1].max(q[1])]
        })?;
        let [s0, s1, s2] = self.sensitivity.0;
        let e = 2.0 * d;
        let bound = 3.0 * e * (s2 + 4.0 * a * s1 + 4.0 * a * a * s0)
            + 3.0 * e * e * (s1 + 2.0 * a * s0)
            + e * e * e * s0;
        // A NaN (non-finite states) gives no certificate.
        bound.is_finite().then_some(bound)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::{Material, NeoHookean};
    use crate::math::{cross, dot};
    use crate::mesh::{MassSpec, TetMesh};
    use crate::model::ModelBuilder;

    /// A bound that holds for random projections of a few tets: the measured changes of J never exceed it.
    #[test]
    fn the_bound_covers_every_tet_s_change_now_and_ahead() {
        let x0 = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
            [1.0, 1.0, 1.0],
        ];
        let (mesh, _) = TetMesh::new(x0.clone(), &[[0, 1, 2, 3], [1, 2, 3, 4]]).unwrap();
        let model = ModelBuilder::new(
            mesh,
            Material::NeoHookean(NeoHookean::new(1e3, 0.3).unwrap()),
        )
        .mass(MassSpec::NodeMass(1.0))
        .build()
        .unwrap();
        let tets: Vec<[usize; 4]> = model.mesh.tets().to_vec();
        let inv: Vec<f64> = model.rest_volume.iter().map(|v| 1.0 / (6.0 * v)).collect();
        let ratio = |x: &[Vec3], t: &[usize; 4], s: f64| {
            let e: Vec<Vec3> = (1..4).map(|k| sub(x[t[k]], x[t[0]])).collect();
            dot(e[0], cross(e[1], e[2])) * s
        };
        let sensitivity = tets
            .iter()
            .zip(&inv)
            .fold(Sensitivity::default(), |s, (t, i)| {
                let longest = (1..4)
                    .map(|k| norm(sub(x0[t[k]], x0[t[0]])))
                    .fold(0.0, f64::max);
                Sensitivity::max(s, Sensitivity::of_tet(longest, *i))
            });
        let mut cert = Certificate::default();
        cert.keep(&model, &x0, sensitivity);
        let mut seed = 7_u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let h = 0.1;
        for _ in 0..200 {
            // The base state: drifted from the kept one, translated, moving; the projection: a small change.
            let xb: Vec<Vec3> = x0
                .iter()
                .map(|p| p.map(|c| c + 3.0 + 0.1 * rnd()))
                .collect();
            let vb: Vec<Vec3> = x0.iter().map(|_| [0.0; 3].map(|_| rnd())).collect();
            let state = State {
                x: xb.iter().map(|p| p.map(|c| c + 0.01 * rnd())).collect(),
                v: vb.iter().map(|p| p.map(|c| c + 0.1 * rnd())).collect(),
                time: 0.0,
            };
            let bound = cert.bound(&model, h, (&xb, &vb), &state).unwrap();
            let ahead = |x: &[Vec3], v: &[Vec3]| -> Vec<Vec3> {
                x.iter()
                    .zip(v)
                    .map(|(p, q)| std::array::from_fn(|k| p[k] + h * q[k]))
                    .collect()
            };
            let (xa, xba) = (ahead(&state.x, &state.v), ahead(&xb, &vb));
            for (t, s) in tets.iter().zip(&inv) {
                assert!((ratio(&state.x, t, *s) - ratio(&xb, t, *s)).abs() <= bound);
                assert!((ratio(&xa, t, *s) - ratio(&xba, t, *s)).abs() <= bound);
            }
        }
        // Another model: no certificate.
        let other = ModelBuilder::new(
            model.mesh.clone(),
            Material::NeoHookean(NeoHookean::new(2e3, 0.3).unwrap()),
        )
        .build()
        .unwrap();
        let state = State::at_rest(&other);
        assert!(cert.bound(&other, h, (&x0, &state.v), &state).is_none());
    }
}

//! The Projective Dynamics (as-rigid-as-possible) strain energy.

use super::{lame_parameters, Hyperelastic, StressDerivative, LANES};
use crate::error::Result;
use crate::math::{inverse, matmul, polar_rotation, transpose, Mat3};

/// The Projective Dynamics strain energy (as-rigid-as-possible, Bouaziz et al. 2014):
/// `Psi = mu |F - R(F)|_F^2`, with `R(F)` the closest rotation (polar decomposition). Its stress is
/// `P = 2 mu (F - R)` (R is optimal, so its variation does not contribute), and
/// `dP = 2 mu (dF - R Omega)`, where the skew `Omega` has axial vector
/// `omega = (tr(S) I - S)^-1 axial(R^T dF - dF^T R)` for `F = R S`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Arap {
    /// Shear modulus `mu`, Pa.
    pub mu: f64,
}

impl Arap {
    /// From Young's modulus (Pa) and Poisson ratio (only `mu` is used: the PD strain energy has no volume term).
    pub fn new(youngs_modulus: f64, poisson_ratio: f64) -> Result<Self> {
        let (mu, _) = lame_parameters(youngs_modulus, poisson_ratio)?;
        Ok(Self { mu })
    }

    /// Energy density and stress given the rotation `r = R(F)`.
    #[inline]
    fn energy_and_stress_given(&self, f: &Mat3, r: &Mat3) -> (f64, Mat3) {
        let mut p = [[0.0; 3]; 3];
        let mut psi = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                let d = f[i][j] - r[i][j];
                psi += d * d;
                p[i][j] = 2.0 * self.mu * d;
            }
        }
        (self.mu * psi, p)
    }
}

impl Hyperelastic for Arap {
    fn energy_density(&self, f: &Mat3) -> f64 {
        self.energy_and_stress(f).0
    }

    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3) {
        self.energy_and_stress_given(f, &polar_rotation(f).0)
    }

    /// The polar decompositions of all lanes in one batch (the PD and FEPR hot path).
    fn energy_density_lanes(&self, f: &[Mat3; LANES], psi: &mut [f64; LANES]) {
        let mut r = [[[0.0; 3]; 3]; LANES];
        crate::math::polar_rotations(f, &mut r);
        for l in 0..LANES {
            psi[l] = self.energy_and_stress_given(&f[l], &r[l]).0;
        }
    }

    fn energy_and_stress_lanes(
        &self,
        f: &[Mat3; LANES],
        psi: &mut [f64; LANES],
        p: &mut [Mat3; LANES],
    ) {
        let mut r = [[[0.0; 3]; 3]; LANES];
        crate::math::polar_rotations(f, &mut r);
        for l in 0..LANES {
            (psi[l], p[l]) = self.energy_and_stress_given(&f[l], &r[l]);
        }
    }

    fn stress_derivative(&self, f: &Mat3) -> StressDerivative {
        let (r, s) = polar_rotation(f);
        let tr = s[0][0] + s[1][1] + s[2][2];
        let mut a = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] = (if i == j { tr } else { 0.0 }) - s[i][j];
            }
        }
        let a_inv = inverse(&a).unwrap_or([[0.0; 3]; 3]);
        let rt = transpose(&r);
        let mut d = [[0.0; 9]; 9];
        for col in 0..9 {
            let mut df = [[0.0; 3]; 3];
            df[col / 3][col % 3] = 1.0;
            // K = R^T dF - dF^T R (skew); axial vector (K21, K02, K10).
            let rtdf = matmul(&rt, &df);
            let k = [
                [0.0, rtdf[0][1] - rtdf[1][0], rtdf[0][2] - rtdf[2][0]],
                [rtdf[1][0] - rtdf[0][1], 0.0, rtdf[1][2] - rtdf[2][1]],
                [rtdf[2][0] - rtdf[0][2], rtdf[2][1] - rtdf[1][2], 0.0],
            ];
            let ax = [k[2][1], k[0][2], k[1][0]];
            let w =
                [0, 1, 2].map(|i| a_inv[i][0] * ax[0] + a_inv[i][1] * ax[1] + a_inv[i][2] * ax[2]);
            let omega = [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]];
            let dr = matmul(&r, &omega);
            for row in 0..9 {
                d[row][col] = 2.0 * self.mu * (df[row / 3][row % 3] - dr[row / 3][row % 3]);
            }
        }
        d
    }
}

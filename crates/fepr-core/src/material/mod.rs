//! Hyperelastic materials: energy density `Psi(F)`, first Piola-Kirchhoff stress `P = dPsi/dF` and its
//! derivative `dP/dF` (9x9, row-major flattening `F[i][j] -> 3*i + j`), all analytic.
//!
//! Parameters are in SI units (Young's modulus in Pa, dimensionless Poisson ratio); energy density in J/m^3.
//! Lame parameters: `mu = E / (2 (1 + nu))`, `lambda = E nu / ((1 + nu)(1 - 2 nu))`.
//!
//! Every material is gated by finite-difference tests of its stress and stress derivative (see `tests`).

mod psd;

pub use psd::*;
mod names;
pub use names::*;

use crate::error::{invalid, Result};
use crate::math::{
    cofactor, ddot, det, inverse, matmul, polar_rotation, svd3, symmetric_eigen_fixed, transpose,
    Mat3,
};

/// A 9x9 stress derivative `dP_ij / dF_kl` at `[3*i + j][3*k + l]`.
pub type StressDerivative = [[f64; 9]; 9];

/// The material interface (after fenris and PBAT): energy density, stress, stress derivative.
pub trait Hyperelastic {
    /// Strain energy density `Psi(F)` in J/m^3; zero at `F = I`.
    fn energy_density(&self, f: &Mat3) -> f64;
    /// First Piola-Kirchhoff stress `P = dPsi/dF` in Pa.
    fn first_piola(&self, f: &Mat3) -> Mat3 {
        self.energy_and_stress(f).1
    }
    /// Energy density and stress together (shares the invariants).
    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3);
    /// Stress derivative `dP/dF` (the energy density's Hessian with respect to F).
    fn stress_derivative(&self, f: &Mat3) -> StressDerivative;
    /// `dP/dF` projected to positive semi-definite (negative eigenvalues clamped to zero). The default
    /// eigen-decomposes the 9x9 matrix ([`crate::material::project_psd`]); materials with a known eigen-system
    /// override it.
    fn stress_derivative_psd(&self, f: &Mat3) -> StressDerivative {
        crate::material::project_psd(&self.stress_derivative(f))
    }
    /// [`Hyperelastic::energy_density`] of [`LANES`] deformation gradients at once, bit for bit the
    /// per-matrix results. The default calls it per matrix; materials whose work vectorises across matrices
    /// override it.
    fn energy_density_lanes(&self, f: &[Mat3; LANES], psi: &mut [f64; LANES]) {
        for (fl, pl) in f.iter().zip(psi.iter_mut()) {
            *pl = self.energy_density(fl);
        }
    }
    /// [`Hyperelastic::energy_and_stress`] of [`LANES`] deformation gradients at once, bit for bit the
    /// per-matrix results (default: per matrix).
    fn energy_and_stress_lanes(
        &self,
        f: &[Mat3; LANES],
        psi: &mut [f64; LANES],
        p: &mut [Mat3; LANES],
    ) {
        for ((fl, pl), sl) in f.iter().zip(p.iter_mut()).zip(psi.iter_mut()) {
            (*sl, *pl) = self.energy_and_stress(fl);
        }
    }
}

/// Deformation gradients per call of the `_lanes` methods of [`Hyperelastic`].
pub const LANES: usize = crate::math::LANES;

/// Lame parameters `(mu, lambda)` from Young's modulus and Poisson ratio, validated
/// (`E > 0` finite, `-1 < nu < 0.5`).
pub fn lame_parameters(youngs_modulus: f64, poisson_ratio: f64) -> Result<(f64, f64)> {
    if !(youngs_modulus.is_finite() && youngs_modulus > 0.0) {
        return Err(invalid(
            "youngs_modulus",
            format!("must be a positive finite number of pascals, got {youngs_modulus}"),
        ));
    }
    if !(poisson_ratio.is_finite() && poisson_ratio > -1.0 && poisson_ratio < 0.5) {
        return Err(invalid(
            "poisson_ratio",
            format!("must satisfy -1 < nu < 0.5 (0.5 is incompressible and not supported), got {poisson_ratio}"),
        ));
    }
    let e = youngs_modulus;
    let nu = poisson_ratio;
    Ok((
        e / (2.0 * (1.0 + nu)),
        e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
    ))
}

/// `d cof(F)_ij / dF_kl = eps_ikn eps_jlq F_nq`: the (F-linear) second derivative of `det F`. Nonzero only
/// for `i != k` and `j != l`, where `n` and `q` are the remaining indices (36 entries).
fn cofactor_derivative(f: &Mat3) -> StressDerivative {
    // eps(a, b, 3 - a - b) for a != b: +1 for (0,1), (1,2), (2,0), -1 otherwise.
    const SIGN: [[f64; 3]; 3] = [[0.0, 1.0, -1.0], [-1.0, 0.0, 1.0], [1.0, -1.0, 0.0]];
    let mut d = [[0.0; 9]; 9];
    for i in 0..3 {
        for k in 0..3 {
            if i == k {
                continue;
            }
            let n = 3 - i - k;
            for j in 0..3 {
                for l in 0..3 {
                    if j == l {
                        continue;
                    }
                    let q = 3 - j - l;
                    d[3 * i + j][3 * k + l] = SIGN[i][k] * SIGN[j][l] * f[n][q];
                }
            }
        }
    }
    d
}

fn flatten(m: &Mat3) -> [f64; 9] {
    [
        m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
    ]
}

/// Natural logarithm shared by the scalar Neo-Hookean and the batched kernel in `elasticity` (both must
/// give the same bits). Positive normal finite inputs go through [`ln_core`] (fdlibm's `e_log.c`, error
/// below 1 ulp); zero, negatives, subnormals, infinities and NaN fall back to `f64::ln`.
#[inline]
pub(crate) fn ln(x: f64) -> f64 {
    if ln_core_applies(x) {
        ln_core(x)
    } else {
        x.ln()
    }
}

/// Whether [`ln_core`] is valid at `x` (positive, normal, finite).
#[inline(always)]
pub(crate) fn ln_core_applies(x: f64) -> bool {
    (f64::MIN_POSITIVE..f64::INFINITY).contains(&x)
}

/// fdlibm's logarithm (`e_log.c`, as in musl before 2018) without branches, so that a loop over it turns
/// into SIMD lanes: `x = 2^k (1 + f)` with `1 + f` in `[sqrt(2)/2, sqrt(2))`, `s = f / (2 + f)`, and
/// `log(1 + f) = f - f^2/2 + s (f^2/2 + R(s^2))` with a degree-14 minimax `R`. Only for positive normal
/// finite `x` (see [`ln_core_applies`]); plain multiplies and adds, no fused multiply-adds.
#[inline(always)]
pub(crate) fn ln_core(x: f64) -> f64 {
    // fdlibm's constants (bits in the comments): ln 2 split so that k * LN2_HI is exact, and the minimax R.
    const LN2_HI: f64 = 0.6931471803691238; // 0x3fe62e42fee00000
    const LN2_LO: f64 = 1.9082149292705877e-10; // 0x3dea39ef35793c76
    const LG1: f64 = 0.6666666666666735; // 0x3fe5555555555593
    const LG2: f64 = 0.3999999999940942; // 0x3fd999999997fa04
    const LG3: f64 = 0.2857142874366239; // 0x3fd2492494229359
    const LG4: f64 = 0.22222198432149784; // 0x3fcc71c51d8e78af
    const LG5: f64 = 0.1818357216161805; // 0x3fc7466496cb03de
    const LG6: f64 = 0.15313837699209373; // 0x3fc39a09d078c69f
    const LG7: f64 = 0.14798198605116586; // 0x3fc2f112df3e5244
                                          // Shift the high word so that the exponent field counts from sqrt(2)/2 rather than 1.
    let bits = x.to_bits();
    let hx = (bits >> 32) + (0x3ff0_0000 - 0x3fe6_a09e);
    let e = (hx >> 20) & 0x7ff;
    let m = (((hx & 0x000f_ffff) + 0x3fe6_a09e) << 32) | (bits & 0xffff_ffff);
    // e as f64 exactly, without an integer conversion (AVX2 has none for 64-bit lanes): 2^52 + e - 2^52.
    let dk = f64::from_bits(0x4330_0000_0000_0000 | e) - (4503599627370496.0 + 1023.0);
    let f = f64::from_bits(m) - 1.0;
    let hfsq = 0.5 * f * f;
    let s = f / (2.0 + f);
    let z = s * s;
    let w = z * z;
    let t1 = w * (LG2 + w * (LG4 + w * LG6));
    let t2 = z * (LG1 + w * (LG3 + w * (LG5 + w * LG7)));
    let r = t2 + t1;
    s * (hfsq + r) + dk * LN2_LO - hfsq + f + dk * LN2_HI
}

/// The seed's log Neo-Hookean, `Psi = mu/2 (tr F^T F - 3) - mu l(J) + lambda/2 l(J)^2`, where `l(J) = log J`
/// for `J >= j0` and its C2 quadratic extension below `j0` (fepr-spec section 4):
/// `l(J) = log j0 + (J - j0)/j0 - (J - j0)^2 / (2 j0^2)`. The extension keeps energy and forces finite and
/// restoring for inverted elements (J <= 0); it is used identically in forces, Hessian and energy.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NeoHookean {
    /// First Lame parameter `mu` (shear modulus), Pa.
    pub mu: f64,
    /// Second Lame parameter `lambda`, Pa.
    pub lambda: f64,
    /// Below this J the logarithm is replaced by its C2 extension (default 0.1).
    pub j0: f64,
}

impl NeoHookean {
    /// Default `j0` of the C2 extension.
    pub const DEFAULT_J0: f64 = 0.1;

    /// From Young's modulus (Pa) and Poisson ratio, with the default `j0 = 0.1`.
    pub fn new(youngs_modulus: f64, poisson_ratio: f64) -> Result<Self> {
        Self::with_j0(youngs_modulus, poisson_ratio, Self::DEFAULT_J0)
    }

    /// From Young's modulus (Pa), Poisson ratio and the extension threshold `0 < j0 <= 1`.
    pub fn with_j0(youngs_modulus: f64, poisson_ratio: f64, j0: f64) -> Result<Self> {
        let (mu, lambda) = lame_parameters(youngs_modulus, poisson_ratio)?;
        if !(j0.is_finite() && j0 > 0.0 && j0 <= 1.0) {
            return Err(invalid("j0", format!("must satisfy 0 < j0 <= 1, got {j0}")));
        }
        Ok(Self { mu, lambda, j0 })
    }

    /// `(l, l', l'')` of the extended logarithm at J.
    #[inline]
    fn extended_log(&self, j: f64) -> (f64, f64, f64) {
        if j >= self.j0 {
            (ln(j), 1.0 / j, -1.0 / (j * j))
        } else {
            let j0 = self.j0;
            let d = j - j0;
            (
                ln(j0) + d / j0 - d * d / (2.0 * j0 * j0),
                1.0 / j0 - d / (j0 * j0),
                -1.0 / (j0 * j0),
            )
        }
    }

    /// Volumetric part `g(J) = -mu l + lambda/2 l^2` and its first two derivatives in J.
    #[inline]
    fn volumetric(&self, j: f64) -> (f64, f64, f64) {
        let (l, dl, ddl) = self.extended_log(j);
        let g = -self.mu * l + 0.5 * self.lambda * l * l;
        let dg = (-self.mu + self.lambda * l) * dl;
        let ddg = self.lambda * dl * dl + (-self.mu + self.lambda * l) * ddl;
        (g, dg, ddg)
    }
}

impl Hyperelastic for NeoHookean {
    fn energy_density(&self, f: &Mat3) -> f64 {
        let ic = ddot(f, f);
        0.5 * self.mu * (ic - 3.0) + self.volumetric(det(f)).0
    }

    #[inline]
    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3) {
        let ic = ddot(f, f);
        let j = det(f);
        let (g, dg, _) = self.volumetric(j);
        let c = cofactor(f);
        let mut p = [[0.0; 3]; 3];
        for i in 0..3 {
            for k in 0..3 {
                p[i][k] = self.mu * f[i][k] + dg * c[i][k];
            }
        }
        (0.5 * self.mu * (ic - 3.0) + g, p)
    }

    fn stress_derivative(&self, f: &Mat3) -> StressDerivative {
        let j = det(f);
        let (_, dg, ddg) = self.volumetric(j);
        let c = flatten(&cofactor(f));
        let mut d = cofactor_derivative(f);
        for a in 0..9 {
            for b in 0..9 {
                d[a][b] = dg * d[a][b] + ddg * c[a] * c[b];
            }
            d[a][a] += self.mu;
        }
        d
    }

    /// Analytic eigen-system (after Smith, de Goes, Kim 2019). With the rotation-variant SVD
    /// `F = U diag(s) V^T` and the orthonormal basis `vec(U E_ij V^T)`, `dP/dF = mu I + g'(J) d2J + g''(J) c c^T`
    /// (`c = cof F`) is block diagonal: for each pair `i < j` (`k` the third index) the twist
    /// `(E_ij - E_ji)/sqrt 2` and flip `(E_ij + E_ji)/sqrt 2` modes have eigenvalues `mu + g' s_k` and
    /// `mu - g' s_k`, and the diagonal modes span the 3x3 block
    /// `mu I + g' [[0, s2, s1], [s2, 0, s0], [s1, s0, 0]] + g'' (s1 s2, s0 s2, s0 s1)(...)^T`.
    /// The projection subtracts `lambda q q^T` for each negative eigenvalue, so an element that is already
    /// positive semi-definite is returned unchanged.
    fn stress_derivative_psd(&self, f: &Mat3) -> StressDerivative {
        let mut d = self.stress_derivative(f);
        let (_, dg, ddg) = self.volumetric(det(f));
        let (u, s, v) = svd3(f);
        // Adds `-lambda vec(U Q V^T) vec(U Q V^T)^T`.
        let mut remove = |lambda: f64, q: &Mat3| {
            let uq = matmul(&u, q);
            let m = matmul(&uq, &transpose(&v));
            let flat = flatten(&m);
            for a in 0..9 {
                let fa = -lambda * flat[a];
                for b in 0..9 {
                    d[a][b] += fa * flat[b];
                }
            }
        };
        let h = std::f64::consts::FRAC_1_SQRT_2;
        for (i, j, k) in [(0, 1, 2), (0, 2, 1), (1, 2, 0)] {
            for (sign, lambda) in [(-1.0, self.mu + dg * s[k]), (1.0, self.mu - dg * s[k])] {
                if lambda < 0.0 {
                    let mut q = [[0.0; 3]; 3];
                    q[i][j] = h;
                    q[j][i] = sign * h;
                    remove(lambda, &q);
                }
            }
        }
        let c = [s[1] * s[2], s[0] * s[2], s[0] * s[1]];
        let mut a3 = [
            [0.0, dg * s[2], dg * s[1]],
            [dg * s[2], 0.0, dg * s[0]],
            [dg * s[1], dg * s[0], 0.0],
        ];
        for (i, row) in a3.iter_mut().enumerate() {
            row[i] += self.mu;
            for (j, x) in row.iter_mut().enumerate() {
                *x += ddg * c[i] * c[j];
            }
        }
        let (w, vecs) = symmetric_eigen_fixed(&a3);
        for (n, &lambda) in w.iter().enumerate() {
            if lambda < 0.0 {
                let mut q = [[0.0; 3]; 3];
                for (i, row) in q.iter_mut().enumerate() {
                    row[i] = vecs[i][n];
                }
                remove(lambda, &q);
            }
        }
        d
    }
}

/// Stable Neo-Hookean (Smith, de Goes, Kim 2018):
/// `Psi = mu'/2 (I_C - 3) + lambda'/2 (J - alpha)^2 - mu'/2 log(I_C + 1) - Psi0`, with
/// `mu' = 4/3 mu`, `lambda' = lambda + 5/6 mu` (matching linear elasticity), `alpha = 1 + mu'/lambda' - mu'/(4 lambda')`,
/// and the constant `Psi0` chosen so that `Psi(I) = 0`. Defined for every F, inverted ones included.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StableNeoHookean {
    /// Reparameterised shear modulus `mu' = 4/3 mu`, Pa.
    pub mu: f64,
    /// Reparameterised bulk term `lambda' = lambda + 5/6 mu`, Pa.
    pub lambda: f64,
    /// Rest-stability offset `alpha`.
    pub alpha: f64,
    /// Energy density of the raw formula at `F = I` (subtracted so that the rest energy is zero).
    pub rest_offset: f64,
}

impl StableNeoHookean {
    /// From Young's modulus (Pa) and Poisson ratio.
    pub fn new(youngs_modulus: f64, poisson_ratio: f64) -> Result<Self> {
        let (mu, lambda) = lame_parameters(youngs_modulus, poisson_ratio)?;
        let mu_s = 4.0 / 3.0 * mu;
        let lambda_s = lambda + 5.0 / 6.0 * mu;
        let alpha = 1.0 + mu_s / lambda_s - mu_s / (4.0 * lambda_s);
        let rest_offset = 0.5 * lambda_s * (1.0 - alpha) * (1.0 - alpha) - 0.5 * mu_s * 4.0f64.ln();
        Ok(Self {
            mu: mu_s,
            lambda: lambda_s,
            alpha,
            rest_offset,
        })
    }
}

impl Hyperelastic for StableNeoHookean {
    fn energy_density(&self, f: &Mat3) -> f64 {
        let ic = ddot(f, f);
        let j = det(f);
        0.5 * self.mu * (ic - 3.0) + 0.5 * self.lambda * (j - self.alpha) * (j - self.alpha)
            - 0.5 * self.mu * (ic + 1.0).ln()
            - self.rest_offset
    }

    #[inline]
    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3) {
        let ic = ddot(f, f);
        let j = det(f);
        let c = cofactor(f);
        let a = self.mu * (1.0 - 1.0 / (ic + 1.0));
        let b = self.lambda * (j - self.alpha);
        let mut p = [[0.0; 3]; 3];
        for i in 0..3 {
            for k in 0..3 {
                p[i][k] = a * f[i][k] + b * c[i][k];
            }
        }
        let psi = 0.5 * self.mu * (ic - 3.0)
            + 0.5 * self.lambda * (j - self.alpha) * (j - self.alpha)
            - 0.5 * self.mu * (ic + 1.0).ln()
            - self.rest_offset;
        (psi, p)
    }

    fn stress_derivative(&self, f: &Mat3) -> StressDerivative {
        let ic = ddot(f, f);
        let j = det(f);
        let c = flatten(&cofactor(f));
        let ff = flatten(f);
        let a = self.mu * (1.0 - 1.0 / (ic + 1.0));
        let bf = 2.0 * self.mu / ((ic + 1.0) * (ic + 1.0));
        let b = self.lambda * (j - self.alpha);
        let mut d = cofactor_derivative(f);
        for r in 0..9 {
            for s in 0..9 {
                d[r][s] = b * d[r][s] + self.lambda * c[r] * c[s] + bf * ff[r] * ff[s];
            }
            d[r][r] += a;
        }
        d
    }
}

/// The Neo-Hookean energy in the constraint form of XPBD (Macklin and Mueller 2021, "A constraint-based
/// formulation of stable Neo-Hookean materials"):
/// `Psi = mu/2 (I_C - 3) + lambda'/2 (J - alpha)^2 - lambda'/2 (alpha - 1)^2`, `alpha = 1 + mu/lambda'`, with
/// `lambda' = lambda + mu` so that it matches linear elasticity at rest, and `Psi(I) = 0`. It is the sum of the
/// energies `C^2 / (2 compliance)` of the two per-element XPBD constraints, deviatoric `C_D = sqrt(I_C)`
/// (compliance `1 / (mu V)`) and hydrostatic `C_H = J - alpha` (compliance `1 / (lambda' V)`), up to the
/// constant: the energy the `xpbd` integrator's compliance encodes (fepr-spec section 5). Defined for every F.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConstraintNeoHookean {
    /// Shear modulus `mu`, Pa.
    pub mu: f64,
    /// `lambda' = lambda + mu`, Pa.
    pub lambda: f64,
    /// Rest-stability offset `alpha = 1 + mu / lambda'`.
    pub alpha: f64,
}

impl ConstraintNeoHookean {
    /// From Young's modulus (Pa) and Poisson ratio.
    pub fn new(youngs_modulus: f64, poisson_ratio: f64) -> Result<Self> {
        let (mu, lambda) = lame_parameters(youngs_modulus, poisson_ratio)?;
        // lambda + mu = E / (2 (1 + nu) (1 - 2 nu)) > 0 for every admissible nu.
        let lambda_s = lambda + mu;
        Ok(Self {
            mu,
            lambda: lambda_s,
            alpha: 1.0 + mu / lambda_s,
        })
    }
}

impl Hyperelastic for ConstraintNeoHookean {
    fn energy_density(&self, f: &Mat3) -> f64 {
        self.energy_and_stress(f).0
    }

    #[inline]
    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3) {
        let ic = ddot(f, f);
        let j = det(f);
        let c = cofactor(f);
        let b = self.lambda * (j - self.alpha);
        let mut p = [[0.0; 3]; 3];
        for i in 0..3 {
            for k in 0..3 {
                p[i][k] = self.mu * f[i][k] + b * c[i][k];
            }
        }
        let a1 = self.alpha - 1.0;
        let psi = 0.5 * self.mu * (ic - 3.0)
            + 0.5 * self.lambda * ((j - self.alpha) * (j - self.alpha) - a1 * a1);
        (psi, p)
    }

    fn stress_derivative(&self, f: &Mat3) -> StressDerivative {
        let j = det(f);
        let c = flatten(&cofactor(f));
        let b = self.lambda * (j - self.alpha);
        let mut d = cofactor_derivative(f);
        for r in 0..9 {
            for s in 0..9 {
                d[r][s] = b * d[r][s] + self.lambda * c[r] * c[s];
            }
            d[r][r] += self.mu;
        }
        d
    }
}

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

/// The materials fepr-core knows, as one enum so that the per-tet loops dispatch statically.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Material {
    NeoHookean(NeoHookean),
    StableNeoHookean(StableNeoHookean),
    /// The Projective Dynamics strain energy (used with the `projective_dynamics` integrator).
    Arap(Arap),
    /// The Neo-Hookean energy of the XPBD constraints (used with the `xpbd` integrator).
    ConstraintNeoHookean(ConstraintNeoHookean),
}

impl Hyperelastic for Material {
    #[inline]
    fn energy_density(&self, f: &Mat3) -> f64 {
        match self {
            Material::NeoHookean(m) => m.energy_density(f),
            Material::StableNeoHookean(m) => m.energy_density(f),
            Material::Arap(m) => m.energy_density(f),
            Material::ConstraintNeoHookean(m) => m.energy_density(f),
        }
    }
    #[inline]
    fn energy_and_stress(&self, f: &Mat3) -> (f64, Mat3) {
        match self {
            Material::NeoHookean(m) => m.energy_and_stress(f),
            Material::StableNeoHookean(m) => m.energy_and_stress(f),
            Material::Arap(m) => m.energy_and_stress(f),
            Material::ConstraintNeoHookean(m) => m.energy_and_stress(f),
        }
    }
    fn stress_derivative(&self, f: &Mat3) -> StressDerivative {
        match self {
            Material::NeoHookean(m) => m.stress_derivative(f),
            Material::StableNeoHookean(m) => m.stress_derivative(f),
            Material::Arap(m) => m.stress_derivative(f),
            Material::ConstraintNeoHookean(m) => m.stress_derivative(f),
        }
    }
    fn stress_derivative_psd(&self, f: &Mat3) -> StressDerivative {
        match self {
            Material::NeoHookean(m) => m.stress_derivative_psd(f),
            Material::StableNeoHookean(m) => m.stress_derivative_psd(f),
            Material::Arap(m) => m.stress_derivative_psd(f),
            Material::ConstraintNeoHookean(m) => m.stress_derivative_psd(f),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples() -> Vec<Mat3> {
        vec![
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            [[1.2, 0.1, -0.05], [0.03, 0.9, 0.2], [-0.1, 0.05, 1.1]],
            // compressed close to, and below, j0 = 0.1
            [[0.5, 0.02, 0.0], [0.0, 0.45, 0.01], [0.03, 0.0, 0.42]],
            [[0.3, 0.1, 0.0], [0.0, 0.3, 0.05], [0.02, 0.0, 0.3]],
            // inverted (J < 0)
            [[-0.8, 0.1, 0.0], [0.05, 1.0, 0.1], [0.0, 0.2, 0.9]],
            // stretched and sheared
            [[1.6, 0.4, 0.2], [-0.3, 1.3, 0.1], [0.2, -0.2, 0.7]],
        ]
    }

    fn materials() -> Vec<Material> {
        vec![
            Material::NeoHookean(NeoHookean::new(1e3, 0.3).unwrap()),
            Material::NeoHookean(NeoHookean::with_j0(5e4, 0.45, 0.3).unwrap()),
            Material::StableNeoHookean(StableNeoHookean::new(1e3, 0.3).unwrap()),
            Material::StableNeoHookean(StableNeoHookean::new(2e5, -0.2).unwrap()),
            Material::Arap(Arap::new(1e3, 0.3).unwrap()),
            Material::ConstraintNeoHookean(ConstraintNeoHookean::new(1e3, 0.3).unwrap()),
            Material::ConstraintNeoHookean(ConstraintNeoHookean::new(5e4, 0.45).unwrap()),
        ]
    }

    fn perturbed(f: &Mat3, idx: usize, h: f64) -> Mat3 {
        let mut g = *f;
        g[idx / 3][idx % 3] += h;
        g
    }

    #[test]
    fn analytic_psd_projection_matches_the_eigen_decomposition() {
        let mut cases = samples();
        cases.extend([
            // repeated singular values (compressed and stretched), a rotation, nearly singular, flat
            [[0.8, 0.0, 0.0], [0.0, 0.8, 0.0], [0.0, 0.0, 1.3]],
            [[1.1, 0.0, 0.0], [0.0, 1.1, 0.0], [0.0, 0.0, 1.1]],
            [[0.0, -0.9, 0.0], [0.9, 0.0, 0.0], [0.0, 0.0, 0.95]],
            [[1.0, 0.2, 0.0], [0.0, 1.0, 0.1], [0.0, 0.0, 1e-7]],
            [[1.0, 0.2, 0.0], [0.0, 1.0, 0.1], [0.0, 0.0, 0.0]],
            [[-0.3, 0.2, 0.1], [0.1, -0.4, 0.1], [0.05, 0.0, -0.2]],
        ]);
        for k in 0..40 {
            let t = k as f64;
            let (a, b, c) = ((0.7 * t).sin(), (1.3 * t).cos(), (0.4 * t).sin());
            cases.push([
                [1.0 + 0.5 * a, 0.3 * b, -0.2 * c],
                [0.2 * c, 0.9 - 0.6 * b * c, 0.25 * a],
                [-0.1 * a, 0.3 * c, 1.0 + 0.4 * b],
            ]);
        }
        for m in [
            NeoHookean::new(1e3, 0.3).unwrap(),
            NeoHookean::with_j0(5e4, 0.45, 0.3).unwrap(),
            NeoHookean::new(1e5, -0.5).unwrap(),
        ] {
            for f in &cases {
                let analytic = m.stress_derivative_psd(f);
                let reference = crate::material::project_psd(&m.stress_derivative(f));
                let scale = reference
                    .iter()
                    .flatten()
                    .fold(0.0f64, |s, v| s.max(v.abs()));
                for r in 0..9 {
                    for c in 0..9 {
                        let err = (analytic[r][c] - reference[r][c]).abs();
                        assert!(
                            err <= 1e-11 * scale,
                            "{m:?} F = {f:?}: [{r}][{c}] {} vs {} (err {err:e})",
                            analytic[r][c],
                            reference[r][c]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn stress_matches_finite_differences_of_energy() {
        for m in materials() {
            for f in samples() {
                let p = m.first_piola(&f);
                for idx in 0..9 {
                    let h = 1e-6;
                    let fd = (m.energy_density(&perturbed(&f, idx, h))
                        - m.energy_density(&perturbed(&f, idx, -h)))
                        / (2.0 * h);
                    let an = p[idx / 3][idx % 3];
                    let scale = 1.0 + an.abs().max(fd.abs());
                    assert!(
                        (fd - an).abs() <= 1e-6 * scale * m_scale(&m),
                        "{m:?} F={f:?} idx {idx}: fd {fd} vs {an}"
                    );
                }
            }
        }
    }

    fn m_scale(m: &Material) -> f64 {
        match m {
            Material::NeoHookean(n) => n.mu + n.lambda.abs(),
            Material::StableNeoHookean(s) => s.mu + s.lambda,
            Material::Arap(a) => a.mu,
            Material::ConstraintNeoHookean(c) => c.mu + c.lambda,
        }
    }

    #[test]
    fn stress_derivative_matches_finite_differences_of_stress() {
        for m in materials() {
            for f in samples() {
                let d = m.stress_derivative(&f);
                for b in 0..9 {
                    let h = 1e-6;
                    let pp = m.first_piola(&perturbed(&f, b, h));
                    let pm = m.first_piola(&perturbed(&f, b, -h));
                    for a in 0..9 {
                        let fd = (pp[a / 3][a % 3] - pm[a / 3][a % 3]) / (2.0 * h);
                        let an = d[a][b];
                        assert!(
                            (fd - an).abs() <= 1e-6 * (1.0 + an.abs()) * m_scale(&m),
                            "{m:?} F={f:?} d[{a}][{b}]: fd {fd} vs {an}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn stress_derivative_is_symmetric() {
        for m in materials() {
            for f in samples() {
                let d = m.stress_derivative(&f);
                for a in 0..9 {
                    for b in 0..9 {
                        assert!(
                            (d[a][b] - d[b][a]).abs()
                                <= 1e-12 * m_scale(&m) * (1.0 + d[a][b].abs()),
                            "{m:?} {a} {b}: {} vs {}",
                            d[a][b],
                            d[b][a]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn rest_state_has_zero_energy_and_stress() {
        let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        for m in materials() {
            let (psi, p) = m.energy_and_stress(&id);
            assert!(psi.abs() < 1e-9 * m_scale(&m), "{m:?}: Psi(I) = {psi}");
            for row in p {
                for x in row {
                    assert!(x.abs() < 1e-9 * m_scale(&m), "{m:?}: P(I) = {p:?}");
                }
            }
        }
    }

    /// The shared logarithm against libm: within 1 ulp over a log-uniform sweep of positive normals (and
    /// exactly at 1, at powers of two and at the special values).
    #[test]
    fn shared_ln_is_within_one_ulp_of_libm() {
        let ulp = |x: f64| f64::from_bits(x.abs().to_bits() + 1) - x.abs();
        let mut worst = 0.0f64;
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        for i in 0..400_000 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let u = (s >> 11) as f64 / (1u64 << 53) as f64;
            // Dense near 1 (where the cancellation is) and log-uniform over the whole normal range.
            let x = if i % 2 == 0 {
                1.0 + (u - 0.5) * 0.6
            } else {
                (2.0f64).powf(-1021.0 + 2044.0 * u)
            };
            let (a, b) = (ln(x), x.ln());
            worst = worst.max((a - b).abs() / ulp(b).max(f64::MIN_POSITIVE));
        }
        assert!(worst <= 1.0, "worst error {worst} ulp");
        assert_eq!(ln(1.0).to_bits(), 0.0f64.to_bits());
        for k in -1020..1020 {
            let x = (2.0f64).powi(k);
            assert!((ln(x) - x.ln()).abs() <= ulp(x.ln()), "2^{k}");
        }
        assert!(ln(0.0) == f64::NEG_INFINITY && ln(f64::INFINITY) == f64::INFINITY);
        assert!(ln(-1.0).is_nan() && ln(f64::NAN).is_nan());
        assert_eq!(ln(1e-310).to_bits(), 1e-310f64.ln().to_bits());
    }

    #[test]
    fn extension_is_c2_at_j0() {
        let m = NeoHookean::new(1e3, 0.3).unwrap();
        let below = m.extended_log(m.j0 * (1.0 - 1e-12));
        let at = m.extended_log(m.j0);
        assert!((below.0 - at.0).abs() < 1e-10);
        assert!((below.1 - at.1).abs() < 1e-8);
        assert!((below.2 - at.2).abs() < 1e-6 * at.2.abs());
    }

    #[test]
    fn inverted_elements_have_finite_restoring_energy() {
        let m = NeoHookean::new(1e3, 0.3).unwrap();
        // Energy decreases from an inverted F towards the identity along a straight path.
        let f_inv = [[-0.5, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let e_inv = m.energy_density(&f_inv);
        assert!(e_inv.is_finite() && e_inv > 0.0);
        let p = m.first_piola(&f_inv);
        // Force on F[0][0] pushes it back up (towards positive J): dPsi/dF00 < 0.
        assert!(p[0][0] < 0.0, "stress {p:?}");
    }

    #[test]
    fn invalid_parameters_are_rejected_with_their_names() {
        assert!(matches!(
            NeoHookean::new(0.0, 0.3),
            Err(crate::FeprError::InvalidParameter {
                name: "youngs_modulus",
                ..
            })
        ));
        assert!(matches!(
            NeoHookean::new(-1.0, 0.3),
            Err(crate::FeprError::InvalidParameter {
                name: "youngs_modulus",
                ..
            })
        ));
        assert!(matches!(
            NeoHookean::new(1e3, 0.5),
            Err(crate::FeprError::InvalidParameter {
                name: "poisson_ratio",
                ..
            })
        ));
        assert!(matches!(
            StableNeoHookean::new(1e3, -1.0),
            Err(crate::FeprError::InvalidParameter {
                name: "poisson_ratio",
                ..
            })
        ));
        assert!(matches!(
            NeoHookean::new(f64::NAN, 0.3),
            Err(crate::FeprError::InvalidParameter {
                name: "youngs_modulus",
                ..
            })
        ));
        assert!(matches!(
            NeoHookean::with_j0(1e3, 0.3, 0.0),
            Err(crate::FeprError::InvalidParameter { name: "j0", .. })
        ));
    }
}

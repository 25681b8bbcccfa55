//! Hyperelastic materials: energy density `Psi(F)`, first Piola-Kirchhoff stress `P = dPsi/dF` and its
//! derivative `dP/dF` (9x9, row-major flattening `F[i][j] -> 3*i + j`), all analytic.
//!
//! Parameters are in SI units (Young's modulus in Pa, dimensionless Poisson ratio); energy density in J/m^3.
//! Lame parameters: `mu = E / (2 (1 + nu))`, `lambda = E nu / ((1 + nu)(1 - 2 nu))`.
//!
//! Layout: this file holds the [`Hyperelastic`] trait, the [`Material`] enum that the per-tet loops dispatch
//! over, and what several models share (Lame parameters, the derivative of the cofactor, the logarithm the
//! batched kernels must match bit for bit); each model has its own file (`neo_hookean`, `stable_neo_hookean`,
//! `constraint_neo_hookean`, `arap`) and [`project_psd`] clamps a stress derivative's eigenvalues (`psd`).
//! Every public name is re-exported here.
//!
//! Every material is gated by finite-difference tests of its stress and stress derivative (`tests` below,
//! over all of [`Material`]); tests of one model's own behaviour sit in its file.

mod arap;
mod constraint_neo_hookean;
mod names;
mod neo_hookean;
mod psd;
mod stable_neo_hookean;

pub use arap::*;
pub use constraint_neo_hookean::*;
pub use names::*;
pub use neo_hookean::*;
pub use psd::*;
pub use stable_neo_hookean::*;

use crate::error::{invalid, Result};
use crate::math::Mat3;

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

    /// Deformation gradients the derivative tests run on (shared with the tests of each model).
    pub(super) fn samples() -> Vec<Mat3> {
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

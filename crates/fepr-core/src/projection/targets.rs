//! What one projection aims at (fepr-spec section 2), and the rounding floor under the rows' tolerances.

use crate::math::{cross, sub, Vec3};

/// Units in the last place that a row's tolerance is never below (with [`rounding_terms`]): a sum of `m`
/// float64 terms of size `S` is only known to about `sqrt(m) eps S`, whatever the tolerance asks.
pub const ROUNDING_ULPS: f64 = 8.0;

/// The growth of the rounding error of a sum over `m` vertices (summed in four lanes): `sqrt(m / 4 + 1)`.
pub fn rounding_terms(m: usize) -> f64 {
    (m as f64 / 4.0 + 1.0).sqrt()
}

/// Targets of one projection (fepr-spec section 2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Targets {
    /// `H_target = H_ref + W`, J.
    pub energy: f64,
    /// `P_target = P_ref + J`, kg m/s.
    pub momentum: Vec3,
    /// `L_target = L_ref + K`, about the target centre of mass, kg m^2/s.
    pub angular_momentum: Vec3,
    /// `C_target`, m.
    pub center_of_mass: Vec3,
    /// The energy row's scale, J: its tolerance is `tolerance * energy_scale`. The simulation measures it on
    /// scales that do not grow with the distance fallen or the time run, and from the start of the step, not
    /// from the base step's result (so a wild base step cannot loosen it): see
    /// [`crate::simulation::Simulation`]'s energy scale.
    pub energy_scale: f64,
    /// The step's impulses are known only approximately (an impulsive event): enables the slack in `Auto`.
    pub uncertain_impulses: bool,
}

impl Targets {
    /// The rigid motion the momentum targets give a body of mass `m` (kg) whose centre of mass is at `center`
    /// (m): its velocity `V = P_target / m` (m/s) and the angular momentum of its spin about `center`,
    /// `L_target - m (center - C_target) x V` (kg m^2/s: the target's angular momentum less what the translation
    /// contributes about the target centre). The one rule the guard's pricing of the momenta, its fallback's
    /// hold on them and the warm start share.
    pub(crate) fn rigid_motion_at(&self, m: f64, center: Vec3) -> (Vec3, Vec3) {
        let velocity = self.momentum.map(|p| p / m);
        let offset = cross(sub(center, self.center_of_mass), velocity);
        let spin = [0, 1, 2].map(|a| self.angular_momentum[a] - m * offset[a]);
        (velocity, spin)
    }
}

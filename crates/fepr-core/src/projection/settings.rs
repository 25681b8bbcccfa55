//! The projection's settings (fepr-spec section 3's defaults) and their validation, with the choices they
//! name: which constraint rows are enforced and when the slack variables move.

use super::Metric;
use crate::error::{invalid, Result};

/// Which constraint rows the projection enforces.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ActiveRows {
    /// `All` for a free body, `Energy` when vertices are pinned (supports exchange momentum with it).
    Auto,
    /// Total energy only.
    Energy,
    /// Energy, linear and angular momentum (the paper's 7 rows).
    EnergyMomentum,
    /// Energy, momenta and centre of mass (10 rows).
    All,
}

impl ActiveRows {
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "auto" => Some(Self::Auto),
            "energy" => Some(Self::Energy),
            "energy_momentum" => Some(Self::EnergyMomentum),
            "all" => Some(Self::All),
            _ => None,
        }
    }
    /// Active-row mask over `[H, Px, Py, Pz, Lx, Ly, Lz, Cx, Cy, Cz]`.
    pub fn mask(self, has_pins: bool) -> [bool; ROWS] {
        let resolved = match self {
            Self::Auto if has_pins => Self::Energy,
            Self::Auto => Self::All,
            other => other,
        };
        let mut m = [false; ROWS];
        m[0] = true;
        if matches!(resolved, Self::EnergyMomentum | Self::All) {
            m[1..7].iter_mut().for_each(|r| *r = true);
        }
        if resolved == Self::All {
            m[7..10].iter_mut().for_each(|r| *r = true);
        }
        m
    }
}

/// Number of constraint rows in total.
pub const ROWS: usize = 10;

/// Projection settings, with the defaults of fepr-spec section 3.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectionSettings {
    /// Relative per-row tolerance (default 1e-10).
    pub tolerance: f64,
    /// Maximum iterations (default 20).
    pub max_iterations: usize,
    /// `eps = c_eps m_tot r^2` weights the slack variables s and t (default 0.01).
    pub c_eps: f64,
    /// Diagonal regularisation of the scaled small system: `delta` times each row's diagonal (default 1e-12).
    pub regularization: f64,
    /// Maximum step halvings per iteration (default 4).
    pub max_halvings: usize,
    /// Which rows are enforced (default `Auto`).
    pub rows: ActiveRows,
    /// Optional cap on the D-norm of the total correction, as a fraction of `sqrt(m_tot) r` (the correction
    /// may move the body by at most this fraction of its size, mass-weighted RMS). `None`: no cap.
    pub impact_bound: Option<f64>,
    /// When the slack variables s and t may move (default `Auto`).
    pub slack: Slack,
    /// Scaled energy error above which (and above `tolerance`) the iterations start from the velocity warm
    /// start (`>= 0`; default: infinity, i.e. off, so that the result is the closest point of fepr-spec
    /// section 3). For dissipative base steps that lose much of H in one step: the Python layer's `"auto"`
    /// uses 0 after Projective Dynamics and 0.05 after XPBD.
    pub warm_start_threshold: f64,
    /// The position block of the metric D (default `Auto`, see [`Metric`]).
    pub metric: Metric,
    /// The quality guard (fepr-spec section 5b; default `Some(0.05)`): restoring an energy deficit may not move
    /// any tet's volume ratio `J`, at the end of the step or one step ahead at the new velocities, by more than
    /// this from what the base step gave it, nor invert a tet the base step left upright. The projection then
    /// restores the largest fraction of the deficit it can within that, and books the rest as unresolved
    /// energy ([`super::ProjectionReport::unresolved`]). `None`: restore everything (the model's own dynamics, which
    /// on sliver tets at large steps inverts them).
    pub quality_margin: Option<f64>,
}

/// When the slack variables s and t of fepr-spec section 2 are free to move.
///
/// With slack, the projection may keep part of the base step's own momentum change (at cost
/// `eps s^2 / 2`) instead of the target: right for steps whose impulses are known only approximately
/// (contact), wrong for a closed system, where the base integrator's momentum error (backward Euler does
/// not conserve angular momentum) would then leak into the result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Slack {
    /// Free only in steps that report an impulsive event with uncertain impulses.
    Auto,
    /// Always free.
    On,
    /// Never: s = t = 0, the momenta are held exactly at their targets.
    Off,
}

impl Slack {
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "auto" => Some(Self::Auto),
            "on" => Some(Self::On),
            "off" => Some(Self::Off),
            _ => None,
        }
    }
}

impl Default for ProjectionSettings {
    fn default() -> Self {
        Self {
            tolerance: 1e-10,
            max_iterations: 20,
            c_eps: 0.01,
            regularization: 1e-12,
            max_halvings: 4,
            rows: ActiveRows::Auto,
            impact_bound: None,
            slack: Slack::Auto,
            warm_start_threshold: f64::INFINITY,
            metric: Metric::Auto,
            quality_margin: Some(DEFAULT_QUALITY_MARGIN),
        }
    }
}

/// The default [`ProjectionSettings::quality_margin`]: a twentieth of the rest volume ratio.
pub const DEFAULT_QUALITY_MARGIN: f64 = 0.05;

impl ProjectionSettings {
    pub fn validate(&self) -> Result<()> {
        if !(self.tolerance.is_finite() && self.tolerance > 0.0 && self.tolerance < 1.0) {
            return Err(invalid(
                "tolerance",
                format!("must satisfy 0 < tolerance < 1, got {}", self.tolerance),
            ));
        }
        if self.max_iterations == 0 || self.max_iterations > 10_000 {
            return Err(invalid(
                "max_iterations",
                format!("must be in 1..=10000, got {}", self.max_iterations),
            ));
        }
        if !(self.c_eps.is_finite() && self.c_eps > 0.0) {
            return Err(invalid(
                "c_eps",
                format!("must be positive and finite, got {}", self.c_eps),
            ));
        }
        if !(self.regularization.is_finite()
            && self.regularization >= 0.0
            && self.regularization < 1.0)
        {
            return Err(invalid(
                "regularization",
                format!("must satisfy 0 <= delta < 1, got {}", self.regularization),
            ));
        }
        if self.warm_start_threshold.is_nan() || self.warm_start_threshold < 0.0 {
            return Err(invalid(
                "warm_start_threshold",
                format!(
                    "must be >= 0 (infinite: off), got {}",
                    self.warm_start_threshold
                ),
            ));
        }
        if let Some(b) = self.impact_bound {
            if !(b.is_finite() && b > 0.0) {
                return Err(invalid(
                    "impact_bound",
                    format!("must be positive and finite, got {b}"),
                ));
            }
        }
        if let Some(q) = self.quality_margin {
            if !(q.is_finite() && q > 0.0 && q <= 1.0) {
                return Err(invalid(
                    "quality_margin",
                    format!("must satisfy 0 < quality_margin <= 1 (a change of the volume ratio J), got {q}"),
                ));
            }
        }
        Ok(())
    }
}

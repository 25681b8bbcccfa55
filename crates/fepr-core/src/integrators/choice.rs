//! An integrator chosen by name with its settings: what a scene file's `[integrator]` table and Python's
//! `fepr.ImplicitEuler(...)`, `fepr.ProjectiveDynamics(...)`, `fepr.Xpbd(...)` describe.

use super::{
    ImplicitEuler, Integrator, NewtonSettings, PdSettings, ProjectiveDynamics, SymplecticEuler,
    Xpbd, XpbdSettings,
};
use crate::error::Result;

/// A base integrator and its settings (each integrator's own defaults by `Default` of its settings).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum IntegratorChoice {
    SymplecticEuler,
    ImplicitEuler(NewtonSettings),
    ProjectiveDynamics(PdSettings),
    Xpbd(XpbdSettings),
}

impl IntegratorChoice {
    /// The integrator `name` (one of [`super::INTEGRATOR_NAMES`]) with default settings.
    pub fn from_name(name: &str) -> Option<Self> {
        Some(match name {
            "symplectic_euler" => Self::SymplecticEuler,
            "implicit_euler" => Self::ImplicitEuler(NewtonSettings::default()),
            "projective_dynamics" => Self::ProjectiveDynamics(PdSettings::default()),
            "xpbd" => Self::Xpbd(XpbdSettings::default()),
            _ => return None,
        })
    }

    /// Its name in [`super::INTEGRATOR_NAMES`].
    pub fn name(&self) -> &'static str {
        match self {
            Self::SymplecticEuler => "symplectic_euler",
            Self::ImplicitEuler(_) => "implicit_euler",
            Self::ProjectiveDynamics(_) => "projective_dynamics",
            Self::Xpbd(_) => "xpbd",
        }
    }

    /// The integrator, its settings checked (errors name the setting).
    pub fn build(self) -> Result<Box<dyn Integrator>> {
        Ok(match self {
            Self::SymplecticEuler => Box::new(SymplecticEuler::new()),
            Self::ImplicitEuler(s) => Box::new(ImplicitEuler::new(s)?),
            Self::ProjectiveDynamics(s) => Box::new(ProjectiveDynamics::new(s)?),
            Self::Xpbd(s) => Box::new(Xpbd::new(s)?),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::integrators::INTEGRATOR_NAMES;

    #[test]
    fn every_listed_integrator_is_a_choice_of_that_name() {
        for n in INTEGRATOR_NAMES {
            let c = IntegratorChoice::from_name(n).expect(n);
            assert_eq!(c.name(), *n);
            assert_eq!(c.build().unwrap().name(), *n);
        }
        assert!(IntegratorChoice::from_name("rk4").is_none());
    }
}

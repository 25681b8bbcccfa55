//! The settings that cross the Python boundary: plain dicts, one per concern (material, mass, integrator,
//! projection, world), read and checked here once. Every error names its key as `section.key` (e.g.
//! `projection.tolerance must satisfy 0 < tolerance < 1, got -1`); the ranges themselves are the core's
//! (`ProjectionSettings::validate`, the integrators' and materials' constructors) where the core checks them.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict};

use fepr_core::integrators::{IntegratorChoice, NewtonSettings, PdSettings, XpbdSettings};
use fepr_core::material::{material_by_name, Material, NeoHookean, MATERIAL_NAMES};
use fepr_core::projection::{
    ActiveRows, Metric, ProjectionSettings, Slack, METRIC_NAMES, ROW_NAMES, SLACK_NAMES,
    WARM_START_MODES,
};
use fepr_core::simulation::auto_warm_start_threshold;
use fepr_core::FeprError;

/// One settings dict with the name of its section, for messages.
pub struct Section<'a, 'py> {
    name: &'static str,
    dict: &'a Bound<'py, PyDict>,
}

fn err(msg: String) -> PyErr {
    PyValueError::new_err(msg)
}

fn repr(v: &Bound<'_, PyAny>) -> String {
    v.repr()
        .map(|r| r.to_string())
        .unwrap_or_else(|_| "?".into())
}

/// A bool (Python's or NumPy's), which Python would otherwise take for 0 or 1.
fn is_bool(v: &Bound<'_, PyAny>) -> bool {
    v.is_instance_of::<PyBool>()
        || v.get_type()
            .name()
            .is_ok_and(|n| n == "bool_" || n == "bool")
}

impl<'a, 'py> Section<'a, 'py> {
    /// The dict `value` as section `name`, with no key outside `known`.
    pub fn new(
        name: &'static str,
        value: &'a Bound<'py, PyAny>,
        known: &[&str],
    ) -> PyResult<Section<'a, 'py>> {
        let dict = value.cast::<PyDict>().map_err(|_| {
            err(format!(
                "{name} must be a dict of settings, got {}",
                repr(value)
            ))
        })?;
        for k in dict.keys() {
            let k: String = k.extract()?;
            if !known.contains(&k.as_str()) {
                return Err(err(format!(
                    "{name}: unknown key '{k}' (known: {})",
                    known.join(", ")
                )));
            }
        }
        Ok(Section { name, dict })
    }

    /// The value of `key`, None when absent (a Python None is a value: only optional settings take it).
    fn get(&self, key: &str) -> PyResult<Option<Bound<'py, PyAny>>> {
        self.dict.get_item(key)
    }

    /// The value of `key`, None when absent or None.
    fn get_some(&self, key: &str) -> PyResult<Option<Bound<'py, PyAny>>> {
        Ok(self.get(key)?.filter(|v| !v.is_none()))
    }

    fn missing(&self, key: &str) -> PyErr {
        err(format!("{}.{key} is required", self.name))
    }

    /// A number (not a bool, not a string), or `default` when absent or None.
    pub fn real(&self, key: &str, default: Option<f64>) -> PyResult<f64> {
        match self.get(key)? {
            None => default.ok_or_else(|| self.missing(key)),
            Some(v) => self.real_value(key, &v),
        }
    }

    fn real_value(&self, key: &str, v: &Bound<'_, PyAny>) -> PyResult<f64> {
        if is_bool(v) || v.is_instance_of::<pyo3::types::PyString>() {
            return Err(err(format!(
                "{}.{key} must be a number, got {}",
                self.name,
                repr(v)
            )));
        }
        v.extract::<f64>().map_err(|_| {
            err(format!(
                "{}.{key} must be a number, got {}",
                self.name,
                repr(v)
            ))
        })
    }

    /// A number that may be absent or None.
    pub fn opt_real(&self, key: &str) -> PyResult<Option<f64>> {
        self.get_some(key)?
            .map(|v| self.real_value(key, &v))
            .transpose()
    }

    /// A non-negative integer (not a bool, not a float), or `default` when absent.
    pub fn count(&self, key: &str, default: Option<usize>) -> PyResult<usize> {
        match self.get(key)? {
            None => default.ok_or_else(|| self.missing(key)),
            Some(v) => {
                let bad = || {
                    err(format!(
                        "{}.{key} must be a non-negative integer, got {}",
                        self.name,
                        repr(&v)
                    ))
                };
                if is_bool(&v) {
                    return Err(bad());
                }
                v.extract::<usize>().map_err(|_| bad())
            }
        }
    }

    /// A count within `lo..=hi` (for bounds the core does not check itself).
    pub fn count_in(&self, key: &str, default: usize, lo: usize, hi: usize) -> PyResult<usize> {
        let n = self.count(key, Some(default))?;
        if n < lo || n > hi {
            return Err(err(format!(
                "{}.{key} must be in {lo}..={hi}, got {n}",
                self.name
            )));
        }
        Ok(n)
    }

    /// A true/false flag, or `default` when absent.
    pub fn flag(&self, key: &str, default: bool) -> PyResult<bool> {
        match self.get(key)? {
            None => Ok(default),
            Some(v) => v.extract::<bool>().map_err(|_| {
                err(format!(
                    "{}.{key} must be true or false, got {}",
                    self.name,
                    repr(&v)
                ))
            }),
        }
    }

    /// One of `choices`, or `default` when absent.
    pub fn choice(&self, key: &str, default: Option<&str>, choices: &[&str]) -> PyResult<String> {
        let bad = |got: String| {
            err(format!(
                "{}.{key} must be one of {}, got {got}",
                self.name,
                choices.join(", ")
            ))
        };
        let s = match self.get(key)? {
            None => return default.map(str::to_owned).ok_or_else(|| self.missing(key)),
            Some(v) => v.extract::<String>().map_err(|_| bad(repr(&v)))?,
        };
        if choices.contains(&s.as_str()) {
            Ok(s)
        } else {
            Err(bad(format!("'{s}'")))
        }
    }

    /// A core error about this section's settings, with the key named `section.key`: the core's own
    /// parameter name, less the prefix it carries when many sections share one namespace (`newton_tolerance`
    /// is `integrator.tolerance`).
    pub fn core_error(&self, e: FeprError) -> PyErr {
        match e {
            FeprError::InvalidParameter { name, message } => {
                let key = ["newton_", "pd_", "xpbd_"]
                    .iter()
                    .find_map(|p| name.strip_prefix(p))
                    .unwrap_or(name);
                err(format!("{}.{key} {message}", self.name))
            }
            other => err(other.to_string()),
        }
    }
}

/// The keys of a material dict.
pub const MATERIAL_KEYS: &[&str] = &["model", "youngs_modulus", "poisson_ratio", "j0"];

/// A material dict: `model` (one of the core's material names), `youngs_modulus` Pa, `poisson_ratio`, `j0`
/// (neo_hookean only; default 0.1). Returns the model name, E, nu, j0 after the core has checked them.
pub fn material(value: &Bound<'_, PyAny>) -> PyResult<(String, f64, f64, f64)> {
    let s = Section::new("material", value, MATERIAL_KEYS)?;
    let model = s.choice("model", None, MATERIAL_NAMES)?;
    let e = s.real("youngs_modulus", None)?;
    let nu = s.real("poisson_ratio", None)?;
    let j0 = s.real("j0", Some(NeoHookean::DEFAULT_J0))?;
    material_by_name(&model, e, nu, j0).map_err(|e| s.core_error(e))?;
    Ok((model, e, nu, j0))
}

/// Build a checked material (for `material_eval`).
pub fn build_material(model: &str, e: f64, nu: f64, j0: f64) -> PyResult<Material> {
    material_by_name(model, e, nu, j0).map_err(|e| err(format!("material.{e}")))
}

/// The keys of an integrator dict (each integrator takes its own subset).
pub const INTEGRATOR_KEYS: &[&str] = &[
    "name",
    "tolerance",
    "max_iterations",
    "iterations",
    "substeps",
];

/// An integrator dict: `name` and that integrator's settings (implicit_euler: `tolerance`,
/// `max_iterations`; projective_dynamics: `iterations`; xpbd: `substeps`, `iterations`), checked by the core.
pub fn integrator(value: &Bound<'_, PyAny>) -> PyResult<IntegratorChoice> {
    let s = Section::new("integrator", value, INTEGRATOR_KEYS)?;
    let name = s.choice("name", None, fepr_core::integrators::INTEGRATOR_NAMES)?;
    let allowed: &[&str] = match name.as_str() {
        "implicit_euler" => &["name", "tolerance", "max_iterations"],
        "projective_dynamics" => &["name", "iterations"],
        "xpbd" => &["name", "substeps", "iterations"],
        _ => &["name"],
    };
    Section::new("integrator", value, allowed).map_err(|_| {
        let extra: Vec<String> = s
            .dict
            .keys()
            .iter()
            .filter_map(|k| k.extract::<String>().ok())
            .filter(|k| !allowed.contains(&k.as_str()))
            .collect();
        err(format!(
            "integrator.{} is not a setting of '{name}' (its settings: {})",
            extra.join(", "),
            allowed[1..].join(", ")
        ))
    })?;
    let choice = match name.as_str() {
        "implicit_euler" => {
            let d = NewtonSettings::default();
            IntegratorChoice::ImplicitEuler(NewtonSettings {
                tolerance: s.real("tolerance", Some(d.tolerance))?,
                max_iterations: s.count("max_iterations", Some(d.max_iterations))?,
                ..d
            })
        }
        "projective_dynamics" => {
            let d = PdSettings::default();
            IntegratorChoice::ProjectiveDynamics(PdSettings {
                iterations: s.count("iterations", Some(d.iterations))?,
                ..d
            })
        }
        "xpbd" => {
            let d = XpbdSettings::default();
            IntegratorChoice::Xpbd(XpbdSettings {
                substeps: s.count("substeps", Some(d.substeps))?,
                iterations: s.count("iterations", Some(d.iterations))?,
            })
        }
        _ => IntegratorChoice::SymplecticEuler,
    };
    choice.build().map_err(|e| s.core_error(e))?;
    Ok(choice)
}

/// The keys of a projection dict (the fields of `fepr.Projection`).
pub const PROJECTION_KEYS: &[&str] = &[
    "tolerance",
    "max_iterations",
    "rows",
    "c_eps",
    "regularization",
    "max_halvings",
    "impact_bound",
    "slack",
    "warm_start",
    "metric",
    "quality_guard",
    "quality_margin",
];

/// The warm start of a projection dict: `"auto"` (the core's policy for the integrator, see
/// `fepr_core::simulation::auto_warm_start_threshold`), `"off"` or None, or a threshold >= 0.
pub enum WarmStart {
    Auto,
    Threshold(f64),
}

/// A projection dict (keys and defaults of `fepr.Projection`), checked by the core; the warm start is
/// resolved against the integrator by [`ProjectionDict::settings_for`].
pub struct ProjectionDict {
    settings: ProjectionSettings,
    warm_start: WarmStart,
}

impl ProjectionDict {
    /// The settings after the integrator named `integrator`.
    pub fn settings_for(&self, integrator: &str) -> ProjectionSettings {
        let warm_start_threshold = match self.warm_start {
            WarmStart::Auto => auto_warm_start_threshold(integrator),
            WarmStart::Threshold(t) => t,
        };
        ProjectionSettings {
            warm_start_threshold,
            ..self.settings
        }
    }
}

pub fn projection(value: &Bound<'_, PyAny>) -> PyResult<ProjectionDict> {
    let s = Section::new("projection", value, PROJECTION_KEYS)?;
    let d = ProjectionSettings::default();
    let rows = s.choice("rows", Some("auto"), ROW_NAMES)?;
    let metric = s.choice("metric", Some("auto"), METRIC_NAMES)?;
    let slack = s.choice("slack", Some("auto"), SLACK_NAMES)?;
    let warm_start = match s.get_some("warm_start")? {
        None => WarmStart::Threshold(f64::INFINITY),
        Some(v) if v.is_instance_of::<pyo3::types::PyString>() => {
            match s.choice("warm_start", None, WARM_START_MODES)?.as_str() {
                "auto" => WarmStart::Auto,
                _ => WarmStart::Threshold(f64::INFINITY),
            }
        }
        Some(v) => {
            let t = s.real_value("warm_start", &v).map_err(|_| {
                err(format!(
                    "projection.warm_start must be a number >= 0, {} or None, got {}",
                    WARM_START_MODES
                        .iter()
                        .map(|m| format!("'{m}'"))
                        .collect::<Vec<_>>()
                        .join(", "),
                    repr(&v)
                ))
            })?;
            WarmStart::Threshold(t)
        }
    };
    let guard = s.flag("quality_guard", true)?;
    let margin = s.real("quality_margin", d.quality_margin)?;
    let mut settings = ProjectionSettings {
        tolerance: s.real("tolerance", Some(d.tolerance))?,
        max_iterations: s.count("max_iterations", Some(d.max_iterations))?,
        c_eps: s.real("c_eps", Some(d.c_eps))?,
        regularization: s.real("regularization", Some(d.regularization))?,
        max_halvings: s.count_in("max_halvings", d.max_halvings, 0, 60)?,
        rows: ActiveRows::from_name(&rows).expect("a listed name"),
        impact_bound: s.opt_real("impact_bound")?,
        slack: Slack::from_name(&slack).expect("a listed name"),
        warm_start_threshold: match warm_start {
            WarmStart::Threshold(t) => t,
            WarmStart::Auto => 0.0,
        },
        metric: Metric::from_name(&metric).expect("a listed name"),
        // The margin is checked whether or not the guard is on.
        quality_margin: Some(margin),
    };
    settings.validate().map_err(|e| s.core_error(e))?;
    if !guard {
        settings.quality_margin = None;
    }
    Ok(ProjectionDict {
        settings,
        warm_start,
    })
}

/// The keys of a world dict.
pub const WORLD_KEYS: &[&str] = &["gravity", "pinned", "damping"];

/// The body's world: `gravity` (3,) m/s^2 (default 0), `pinned` vertex indices (default none), `damping` the
/// velocity damping factor per step in [0, 1) (default 0; checked by the core's model builder).
pub fn world(value: &Bound<'_, PyAny>) -> PyResult<([f64; 3], Vec<usize>, f64)> {
    let s = Section::new("world", value, WORLD_KEYS)?;
    let gravity = match s.get_some("gravity")? {
        None => [0.0; 3],
        Some(v) => v.extract::<[f64; 3]>().map_err(|_| {
            err(format!(
                "world.gravity must be three numbers, got {}",
                repr(&v)
            ))
        })?,
    };
    let pinned = match s.get_some("pinned")? {
        None => Vec::new(),
        Some(v) => v.extract::<Vec<usize>>().map_err(|_| {
            err(format!(
                "world.pinned must be a list of vertex indices, got {}",
                repr(&v)
            ))
        })?,
    };
    let damping = s.real("damping", Some(0.0))?;
    Ok((gravity, pinned, damping))
}

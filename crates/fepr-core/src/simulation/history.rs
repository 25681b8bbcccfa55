//! The per-step diagnostics as a table: the column names (one list, read by the Python bindings and the CLI)
//! and one [`StepDiagnostics`] as a row of them.

use super::StepDiagnostics;

/// The names of the diagnostics columns, in the order of [`history_row`] (Python: `Simulation.history`,
/// CLI: `diagnostics.csv`; every column is described in `docs/concepts.md`).
pub const HISTORY_COLUMNS: [&str; 59] = [
    "base_iterations",
    "base_residual",
    "base_line_search",
    "step",
    "time",
    "kinetic",
    "elastic",
    "gravitational",
    "total",
    "px",
    "py",
    "pz",
    "lx",
    "ly",
    "lz",
    "cx",
    "cy",
    "cz",
    "proj_iterations",
    "proj_converged",
    "proj_residual",
    "proj_initial_residual",
    "proj_correction",
    "proj_fallback",
    "proj_bound_hit",
    "proj_s",
    "proj_t",
    "base_ms",
    "proj_ms",
    "min_j",
    "inverted",
    "budget",
    "base_energy_error",
    "runaway",
    "proj_warm_start",
    "budget_total",
    "contacts",
    "penetration",
    "work_contact",
    "work_damping",
    "work_pins",
    "work_forces",
    "proj_frozen",
    "base_substeps",
    "proj_evaluations",
    "work_unresolved",
    "proj_restored",
    "proj_trials",
    "proj_metric_switched",
    "proj_quality_excess",
    "px_target",
    "py_target",
    "pz_target",
    "lx_target",
    "ly_target",
    "lz_target",
    "proj_gap",
    "proj_stood_down",
    "work_deferred",
];

/// The columns of [`HISTORY_COLUMNS`] that hold counts or 0/1 flags (integer-valued floats in a row; written as
/// integers in CSV).
pub const HISTORY_INTEGER_COLUMNS: &[&str] = &[
    "base_iterations",
    "base_line_search",
    "base_substeps",
    "step",
    "proj_iterations",
    "proj_converged",
    "proj_fallback",
    "proj_bound_hit",
    "proj_warm_start",
    "proj_frozen",
    "proj_evaluations",
    "proj_trials",
    "proj_metric_switched",
    "proj_stood_down",
    "inverted",
    "runaway",
    "contacts",
];

/// One step's diagnostics as a row of [`HISTORY_COLUMNS`]: counts and flags as integer-valued floats, the
/// projection's reals NaN in a step without a projection.
pub fn history_row(d: &StepDiagnostics) -> [f64; HISTORY_COLUMNS.len()] {
    let i = &d.invariants;
    let lt = d.angular_momentum_target();
    let p = d.projection.unwrap_or_default();
    let has = d.projection.is_some();
    let nan_if = |x: f64| if has { x } else { f64::NAN };
    [
        d.base.iterations as f64,
        d.base.residual,
        d.base.line_search_steps as f64,
        d.step as f64,
        d.time,
        i.kinetic,
        i.elastic,
        i.gravitational,
        i.total,
        i.momentum[0],
        i.momentum[1],
        i.momentum[2],
        i.angular_momentum[0],
        i.angular_momentum[1],
        i.angular_momentum[2],
        i.center_of_mass[0],
        i.center_of_mass[1],
        i.center_of_mass[2],
        if has { p.iterations as f64 } else { 0.0 },
        if has { p.converged as u8 as f64 } else { 0.0 },
        nan_if(p.final_residual),
        nan_if(p.initial_residual),
        nan_if(p.correction),
        if has { p.fallback as u8 as f64 } else { 0.0 },
        if has { p.bound_hit as u8 as f64 } else { 0.0 },
        nan_if(p.s),
        nan_if(p.t),
        d.base_ms,
        d.proj_ms,
        i.min_j,
        i.inverted as f64,
        d.energy_budget,
        d.base_energy_error,
        d.runaway as u8 as f64,
        if has { p.warm_start as u8 as f64 } else { 0.0 },
        d.budget_total,
        d.contacts as f64,
        d.penetration,
        d.work.contact,
        d.work.damping,
        d.work.pins,
        d.work.forces,
        if has { p.frozen_vertices as f64 } else { 0.0 },
        d.base.substeps as f64,
        if has { p.evaluations as f64 } else { 0.0 },
        d.work.unresolved,
        nan_if(p.restored),
        if has { p.trials as f64 } else { 0.0 },
        if has {
            p.metric_switched as u8 as f64
        } else {
            0.0
        },
        nan_if(p.quality_excess),
        d.references.momentum[0],
        d.references.momentum[1],
        d.references.momentum[2],
        lt[0],
        lt[1],
        lt[2],
        nan_if(p.gap),
        if has { p.stood_down as u8 as f64 } else { 0.0 },
        d.work.deferred,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn columns_are_distinct_and_integer_columns_are_columns() {
        let mut c = HISTORY_COLUMNS.to_vec();
        c.sort_unstable();
        c.dedup();
        assert_eq!(c.len(), HISTORY_COLUMNS.len());
        for i in HISTORY_INTEGER_COLUMNS {
            assert!(HISTORY_COLUMNS.contains(i), "{i}");
        }
    }
}

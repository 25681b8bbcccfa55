//! The projection's names as users spell them (Python keywords, scene-file values): the constraint-row
//! choices, the metrics, the slack modes, the warm-start modes and the fields of a [`ProjectionReport`].
//! These lists are the one source; the Python bindings export them (`fepr._core.PROJECTION_ROWS`, ...).

use super::ProjectionReport;

/// The names [`super::ActiveRows::from_name`] accepts, in the order of the variants.
pub const ROW_NAMES: &[&str] = &["auto", "energy", "energy_momentum", "all"];

/// The names [`super::Metric::from_name`] accepts.
pub const METRIC_NAMES: &[&str] = &["auto", "mass", "stiffness"];

/// The names [`super::Slack::from_name`] accepts.
pub const SLACK_NAMES: &[&str] = &["auto", "on", "off"];

/// The named warm-start modes (besides a number, the scaled energy error above which the warm start runs):
/// `"auto"` chooses the threshold from the base integrator (`crate::simulation::auto_warm_start_threshold`),
/// `"off"` never warm-starts.
pub const WARM_START_MODES: &[&str] = &["auto", "off"];

/// The fields of a projection report as the bindings hand them out (Python: `Simulation.last_projection()`
/// and `fepr.ProjectionReport`), in the order of [`report_values`].
pub const REPORT_FIELDS: [&str; 27] = [
    "iterations",
    "converged",
    "residual",
    "initial_residual",
    "correction",
    "s",
    "t",
    "fallback",
    "bound_hit",
    "least_squares_solves",
    "halvings",
    "active_rows",
    "base_energy",
    "warm_start",
    "stiffness_metric",
    "system_metric",
    "restarts",
    "frozen_vertices",
    "evaluations",
    "restored",
    "unresolved",
    "trials",
    "metric_switched",
    "quality_excess",
    "gap",
    "translated",
    "stood_down",
];

/// One value of a projection report, typed as the user sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ReportValue {
    Count(usize),
    Flag(bool),
    Real(f64),
}

/// The values of [`REPORT_FIELDS`] for `r`, in that order.
pub fn report_values(r: &ProjectionReport) -> [ReportValue; REPORT_FIELDS.len()] {
    use ReportValue::{Count, Flag, Real};
    [
        Count(r.iterations),
        Flag(r.converged),
        Real(r.final_residual),
        Real(r.initial_residual),
        Real(r.correction),
        Real(r.s),
        Real(r.t),
        Flag(r.fallback),
        Flag(r.bound_hit),
        Count(r.least_squares_solves),
        Count(r.halvings),
        Count(r.active_rows),
        Real(r.base_energy),
        Flag(r.warm_start),
        Flag(r.stiffness_metric),
        Flag(r.system_metric),
        Count(r.restarts),
        Count(r.frozen_vertices),
        Count(r.evaluations),
        Real(r.restored),
        Real(r.unresolved),
        Count(r.trials),
        Flag(r.metric_switched),
        Real(r.quality_excess),
        Real(r.gap),
        Flag(r.translated),
        Flag(r.stood_down),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::projection::{ActiveRows, Metric, Slack};

    #[test]
    fn every_listed_name_parses_and_nothing_else() {
        for n in ROW_NAMES {
            assert!(ActiveRows::from_name(n).is_some(), "{n}");
        }
        for n in METRIC_NAMES {
            assert!(Metric::from_name(n).is_some(), "{n}");
        }
        for n in SLACK_NAMES {
            assert!(Slack::from_name(n).is_some(), "{n}");
        }
        for bad in ["", "Auto", "none", "energy-momentum"] {
            assert!(ActiveRows::from_name(bad).is_none());
            assert!(Metric::from_name(bad).is_none());
            assert!(Slack::from_name(bad).is_none());
        }
    }

    #[test]
    fn report_fields_are_distinct() {
        let mut f = REPORT_FIELDS.to_vec();
        f.sort_unstable();
        f.dedup();
        assert_eq!(f.len(), REPORT_FIELDS.len());
    }
}

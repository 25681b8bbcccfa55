//! Minimisation along a segment by golden-section search (the contacts' crossing and edge tests).
//!
//! Written here: a dozen lines that no maintained crate offers on plain closures without pulling in an
//! optimisation framework, and both callers need to stop early on their own condition.

/// Golden-section search for the minimum of `f` on `[0, 1]`, unimodal there: shrinks the bracket until it is
/// narrower than `tol` or `stop` holds for a probe's value. Returns the two last probes `(t, f(t))`, the lower
/// first.
pub fn golden_section(
    f: impl Fn(f64) -> f64,
    tol: f64,
    stop: impl Fn(f64) -> bool,
) -> [(f64, f64); 2] {
    let inv_golden = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut b) = (0.0f64, 1.0f64);
    let (mut c, mut d) = (b - inv_golden * (b - a), a + inv_golden * (b - a));
    let (mut fc, mut fd) = (f(c), f(d));
    while b - a > tol && !(stop(fc) || stop(fd)) {
        if fc < fd {
            b = d;
            (d, fd) = (c, fc);
            c = b - inv_golden * (b - a);
            fc = f(c);
        } else {
            a = c;
            (c, fc) = (d, fd);
            d = a + inv_golden * (b - a);
            fd = f(d);
        }
    }
    [(c, fc), (d, fd)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_minimum_of_a_unimodal_function_and_stops_on_request() {
        let f = |t: f64| (t - 0.3).abs() + 0.1;
        let [(c, fc), (d, fd)] = golden_section(f, 1e-9, |_| false);
        let best = if fc <= fd { c } else { d };
        assert!((best - 0.3).abs() < 1e-8, "{best}");
        // Stopped at the first probe below 0.5: the first probes are at 0.382 and 0.618.
        let [(c, fc), _] = golden_section(f, 1e-9, |v| v < 0.5);
        assert!((c - 0.381_966).abs() < 1e-5 && fc < 0.5, "{c} {fc}");
    }
}

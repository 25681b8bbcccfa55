//! Contact between bodies as constraints of the bodies' joint global step, for integrators whose step is a
//! sequence of linear solves ([`CoupledSolve`], Projective Dynamics).
//!
//! A surface vertex `i` of body A near the triangle `(j)` of body B (barycentric weights `w_j`, B's outward
//! normal `n`) is the constraint row `s = (e_i - sum_j w_j e_j) (x) n`: its gap
//! `s . x = n . (x_i - sum_j w_j x_j)` must not be negative. The rows enter each iteration's global step as
//! the stiff penalty `k/2 (s . x)^2` on the rows that would otherwise end negative (an active set, with
//! `k = ROW_STIFFNESS_RATIO / (h^2 K)`, `K` the row's effective inverse mass): the joint matrix is the bodies'
//! own, block diagonal, plus a low-rank coupling, so each iteration solves it exactly through the
//! Sherman-Morrison-Woodbury identity with the bodies' own factorisations: with `y` the bodies' unconstrained
//! solutions, `z_r = A^{-1} s_r` (from the columns `A^{-1} e_v` of the vertices the rows touch, one solve per
//! vertex, once per step and matrix) and the small dense system `(I/k + S^T Z) mu = -S^T y`, the solution is
//! `x = y + Z mu`, and `mu_r` is the row's force (N). Rows whose force would pull (`mu_r < 0`) leave the set;
//! rows that would end negative join it. Each iteration takes a row's triangle, weights and normal again from
//! the current iterates (the vertex slides over the other's surface), unless the vertex is deeper than the
//! impact limit (then the face it is nearest to is not the one it came through, and the row keeps the face it
//! was found against at the start of the step). A vertex squeezed into an obstacle gets a row against it too
//! (the obstacle's side does not move). A pushing row also carries Coulomb friction, a force in its tangent plane
//! that aims at no sliding over the step within the cone `|f_t| <= mu f_n` ([`BodyConstraints::add_friction`]).
//!
//! Why: the force is one scalar per row acting on both bodies (`+mu n` on the vertex, `-w_j mu n` on the
//! triangle's corners), so the bodies' momenta change by equal and opposite amounts in every iteration; each
//! body's solve carries the support to the whole body within the step, so an impact needs no parts and a
//! resting pile no push-out (which strains the surface layer and, in a pile, pumps it). Why not hold each
//! body against the other's frozen surface (Jacobi): the two solves then disagree about the force (a heavy
//! body is stopped, a light one receives all of it), the momenta drift and energy is created.
//! A hand-written solve: no maintained crate offers a Woodbury update over several sparse factorisations.

use crate::integrators::CoupledSolve;
use crate::invariants::center_of_mass;
use crate::math::{add, cross, dot, norm, scale, sub, Vec3};
use crate::world::{
    body_contact_pairs, body_pairs_at, BodyExchange, BodyIterate, BodyPair, RESTING_SPEED_STEPS,
};

use super::{BodyCoefficients, Simulation};

/// One constraint row between two bodies, or between a body and an obstacle (`obstacle`: its index; then
/// only the pair's body, vertex, normal and point mean anything: the obstacle does not move).
struct Row {
    pair: BodyPair,
    obstacle: Option<usize>,
    /// The relative normal velocity of the pair's points at the start of the step (m/s, negative: approach).
    approach_speed: f64,
    /// Its force in the last iteration (N; 0 when not in the active set).
    force: f64,
    /// Its friction force in the last iteration (N, perpendicular to the normal then).
    friction: Vec3,
}

/// Rows that couple only among themselves ([`BodyConstraints::blocks`]): their indices, ascending, and their
/// scalar coupling (local, row-major).
#[derive(Default)]
struct Block {
    rows: Vec<usize>,
    coupling: Vec<f64>,
}

/// The constraint rows of a step among bodies and the bodies' solve layouts.
pub(super) struct BodyConstraints {
    rows: Vec<Row>,
    /// Per body, the row (in its solution) of each vertex, `u32::MAX` for pinned ones.
    row_of: Vec<Vec<u32>>,
    /// Per body and vertex, the column `A^{-1} e_v` (one value per free vertex) once solved.
    columns: Vec<Vec<Option<Box<[f64]>>>>,
    /// Per body, its matrix version when its columns were solved.
    versions: Vec<usize>,
    /// Per body, whether it is done iterating (in the current correction).
    frozen: Vec<bool>,
    h: f64,
    /// Rows deeper than this keep their face (m).
    limit: f64,
    /// Per body, the velocities at the start of the part (m/s), for the rows' work.
    v_start: Vec<Vec<Vec3>>,
    /// Per body, its Coulomb friction coefficient against other bodies (a pair takes the geometric mean).
    friction: Vec<f64>,
}

fn coupled(sim: &mut Simulation) -> &mut dyn CoupledSolve {
    sim.integrator
        .coupled()
        .expect("bodies take their solves together only when every integrator can")
}

/// The bodies' current iterates (`start`: their states' positions instead) as contact sees them.
fn iterates<'a>(sims: &'a mut [&mut Simulation], start: bool) -> Vec<BodyIterate<'a>> {
    sims.iter_mut()
        .map(|sim| {
            let Simulation {
                integrator,
                model,
                state,
                surface,
                ..
            } = &mut **sim;
            BodyIterate {
                model,
                x: if start {
                    &state.x
                } else {
                    integrator.coupled().expect("coupled").positions()
                },
                surface: surface.as_mut().expect("surfaces are built first"),
            }
        })
        .collect()
}

/// A contact between two bodies that another solve held (backward Euler's joint Newton,
/// [`super::body_newton`]), as the books take it: its pair's geometry, the approach speed at the start of the
/// step (m/s, negative: approach), its normal force (N) and friction force (N, on the vertex) at the end.
pub(super) struct HeldRow {
    pub pair: BodyPair,
    pub approach_speed: f64,
    pub force: f64,
    pub friction: Vec3,
}

impl BodyConstraints {
    /// The books of rows held by another solve over the step `h` ([`BodyConstraints::exchanges`] then gives
    /// what they exchanged); `v_start`: each body's velocities at the start of the step.
    pub(super) fn booking(
        rows: Vec<HeldRow>,
        h: f64,
        v_start: Vec<Vec<Vec3>>,
        coefficients: &[BodyCoefficients],
    ) -> Self {
        Self {
            rows: rows
                .into_iter()
                .map(|r| Row {
                    pair: r.pair,
                    obstacle: None,
                    approach_speed: r.approach_speed,
                    force: r.force,
                    friction: r.friction,
                })
                .collect(),
            row_of: Vec::new(),
            columns: Vec::new(),
            versions: Vec::new(),
            frozen: Vec::new(),
            h,
            limit: 0.0,
            v_start,
            friction: coefficients.iter().map(|c| c.friction).collect(),
        }
    }

    /// No rows yet; the bodies' steps are begun. `limit`: the impact limit (m); `coefficients`: the bodies'
    /// contact coefficients (their frictions against each other).
    pub(super) fn new(
        sims: &mut [&mut Simulation],
        h: f64,
        limit: f64,
        coefficients: &[BodyCoefficients],
    ) -> Self {
        let mut row_of = Vec::with_capacity(sims.len());
        let mut versions = Vec::with_capacity(sims.len());
        let mut columns = Vec::with_capacity(sims.len());
        for sim in sims.iter_mut() {
            let m = sim.model.num_vertices();
            let solve = coupled(sim);
            let mut rows = vec![u32::MAX; m];
            for (r, v) in solve.free_vertices().into_iter().enumerate() {
                rows[v] = r as u32;
            }
            row_of.push(rows);
            versions.push(solve.matrix_version());
            columns.push(vec![None; m]);
        }
        Self {
            rows: Vec::new(),
            v_start: sims.iter().map(|s| s.state.v.clone()).collect(),
            frozen: vec![false; row_of.len()],
            row_of,
            columns,
            versions,
            h,
            limit,
            friction: coefficients.iter().map(|c| c.friction).collect(),
        }
    }

    /// Add the rows of the surface vertices within `margin` (m) of another body at the current iterates. A
    /// vertex new to the rows takes its face from the start of the step (where both sides were apart, or
    /// nearly: a vertex the prediction puts deep inside is nearest to a face it never crossed), unless it was
    /// inside already; a vertex inside another body through a face none of its rows has (a crease, or the
    /// dimple its push makes) gets a row for that face too (at most [`ROWS_PER_VERTEX`]; then it replaces the
    /// row that pushes least). Returns the
    /// deepest any surface vertex lies inside another body at the current iterates (m, 0 when none does).
    pub(super) fn detect(&mut self, sims: &mut [&mut Simulation], margin: f64) -> f64 {
        let found = body_contact_pairs(&mut iterates(sims, false), margin);
        let deepest = found.iter().map(|p| p.depth).fold(0.0, f64::max);
        let mut fresh = Vec::new();
        let mut creases = Vec::new();
        for pair in found {
            let rows: Vec<usize> = (0..self.rows.len())
                .filter(|&r| {
                    let q = &self.rows[r].pair;
                    self.rows[r].obstacle.is_none()
                        && q.body == pair.body
                        && q.vertex == pair.vertex
                        && q.other == pair.other
                })
                .collect();
            if rows.is_empty() {
                fresh.push(pair);
            } else if pair.depth > 0.0
                && rows
                    .iter()
                    .all(|&r| self.rows[r].pair.triangle != pair.triangle)
            {
                if rows.len() < ROWS_PER_VERTEX {
                    creases.push(pair);
                } else {
                    // The face the vertex is inside now replaces its row that pushes least.
                    let weakest = rows
                        .into_iter()
                        .min_by(|&a, &b| self.rows[a].force.total_cmp(&self.rows[b].force))
                        .expect("rows");
                    self.rows[weakest].pair = pair;
                    self.rows[weakest].force = 0.0;
                    self.rows[weakest].friction = [0.0; 3];
                }
            }
        }
        let candidates: Vec<(usize, usize, usize)> =
            fresh.iter().map(|p| (p.body, p.vertex, p.other)).collect();
        let at_start = body_pairs_at(&mut iterates(sims, true), &candidates);
        let chosen: Vec<BodyPair> = fresh
            .into_iter()
            .zip(at_start)
            .map(|(now, start)| if start.depth > 0.0 { now } else { start })
            .chain(creases)
            .collect();
        for pair in chosen {
            let (va, vb) = (&sims[pair.body].state.v, &sims[pair.other].state.v);
            let vp = (0..3).fold([0.0; 3], |s, c| {
                add(s, scale(vb[pair.triangle[c]], pair.weights[c]))
            });
            let approach_speed = dot(sub(va[pair.vertex], vp), pair.normal);
            self.rows.push(Row {
                pair,
                obstacle: None,
                approach_speed,
                force: 0.0,
                friction: [0.0; 3],
            });
        }
        deepest.max(self.detect_obstacles(sims))
    }

    /// Rows for the surface vertices within `margin` (m) of an obstacle or inside it, at the current iterates
    /// (one per vertex and obstacle): among bodies in contact a vertex is squeezed between another body's rows
    /// and an obstacle, and the obstacle's own constraint (a stiffness in the body's matrix, softer than a row)
    /// would give way.
    /// Returns the deepest a surface vertex lies inside an obstacle (m, 0 when none does).
    fn detect_obstacles(&mut self, sims: &mut [&mut Simulation]) -> f64 {
        let mut deepest: f64 = 0.0;
        for (k, sim) in sims.iter_mut().enumerate() {
            if sim.world.obstacles.is_empty() {
                continue;
            }
            let Simulation {
                integrator,
                surface,
                model,
                world,
                state,
                ..
            } = &mut **sim;
            let surface = surface.as_ref().expect("surfaces are built first");
            let x = integrator.coupled().expect("coupled").positions();
            let mut found = Vec::new();
            for &v in surface.vertices() {
                let v = v as usize;
                if model.pinned[v] {
                    continue;
                }
                for (o, ob) in world.obstacles.iter().enumerate() {
                    if let Some((phi, n)) = ob.signed_distance_below(x[v], 0.0) {
                        // Shallow ones are the obstacle's own constraint's (in the body's matrix).
                        if -phi > SHALLOW * self.limit {
                            found.push((v, o, phi, n));
                        }
                    } else if let Some((_, _, n)) = ob.first_crossing(state.x[v], x[v]) {
                        // Through a thin obstacle within the step: its row holds the face it came in by.
                        found.push((v, o, 0.0, n));
                    }
                }
            }
            for (v, o, phi, n) in found {
                deepest = deepest.max(-phi);
                if self
                    .rows
                    .iter()
                    .any(|r| r.obstacle == Some(o) && r.pair.body == k && r.pair.vertex == v)
                {
                    continue;
                }
                let vel = sim.state.v[v];
                // The face the vertex came from when it started outside (a thin obstacle's far face is nearer
                // to a vertex that went more than half through it), where a moving obstacle has carried it.
                let start = sim.state.x[v];
                let xv = coupled(sim).positions()[v];
                let ob = &sim.world.obstacles[o];
                let (phi0, n0) = ob.signed_distance_at_start(start);
                let (phi, n, point) = if phi0 >= 0.0 {
                    let (point, n0) = ob.carried_over_step(sub(start, scale(n0, phi0)), n0);
                    (dot(n0, sub(xv, point)), n0, point)
                } else {
                    (phi, n, sub(xv, scale(n, phi)))
                };
                // Approach relative to the obstacle's surface.
                let vel = sub(vel, ob.velocity_at(point));
                self.rows.push(Row {
                    pair: BodyPair {
                        body: k,
                        vertex: v,
                        other: k,
                        triangle: [v; 3],
                        weights: [0.0; 3],
                        normal: n,
                        depth: -phi,
                        point,
                        inverse_mass: 1.0 / sim.model.masses[v],
                    },
                    obstacle: Some(o),
                    approach_speed: dot(vel, n),
                    force: 0.0,
                    friction: [0.0; 3],
                });
            }
        }
        deepest
    }

    /// Take every row's geometry again from the current iterates, unless its vertex is deeper than the limit.
    fn follow(&mut self, sims: &mut [&mut Simulation]) {
        if self.rows.is_empty() {
            return;
        }
        for row in self.rows.iter_mut() {
            if let Some(o) = row.obstacle {
                let sim = &mut *sims[row.pair.body];
                let x = coupled(sim).positions()[row.pair.vertex];
                let (phi, n) = sim.world.obstacles[o].signed_distance(x);
                if -phi < self.limit {
                    row.pair.normal = n;
                    row.pair.depth = -phi;
                    row.pair.point = sub(x, scale(n, phi));
                }
            }
        }
        let between: Vec<usize> = (0..self.rows.len())
            .filter(|&r| self.rows[r].obstacle.is_none())
            .collect();
        let candidates: Vec<(usize, usize, usize)> = between
            .iter()
            .map(|&r| {
                let p = &self.rows[r].pair;
                (p.body, p.vertex, p.other)
            })
            .collect();
        let now = body_pairs_at(&mut iterates(sims, false), &candidates);
        let single: Vec<bool> = candidates
            .iter()
            .map(|c| candidates.iter().filter(|d| *d == c).count() == 1)
            .collect();
        for ((&r, pair), single) in between.iter().zip(now).zip(single) {
            let row = &mut self.rows[r];
            // A vertex with several rows keeps their faces (each is one side of its crease).
            if row.pair.triangle == pair.triangle || (single && pair.depth < self.limit) {
                row.pair = pair;
            }
        }
    }

    /// Solve the columns the rows need on every body (all again on a body whose matrix changed), the bodies at
    /// once (each reads only its own factorisation: the same bits in any order).
    fn solve_columns(&mut self, sims: &mut [&mut Simulation]) {
        let nb = sims.len();
        let mut needed: Vec<Vec<usize>> = vec![Vec::new(); nb];
        for r in &self.rows {
            let p = &r.pair;
            needed[p.body].push(p.vertex);
            if r.obstacle.is_none() {
                needed[p.other].extend(p.triangle.iter());
            }
        }
        let mut bodies: Vec<_> = sims
            .iter_mut()
            .zip(needed)
            .zip(self.columns.iter_mut())
            .zip(self.versions.iter_mut())
            .zip(self.row_of.iter().zip(&self.frozen))
            .map(|((((sim, needed), columns), version), (row_of, &frozen))| {
                (&mut **sim, needed, columns, version, row_of, frozen)
            })
            .collect();
        crate::exec::for_each_mut(
            &mut bodies,
            |_, (sim, needed, columns, version, row_of, frozen)| {
                if *frozen {
                    return;
                }
                let solve = coupled(sim);
                let now = solve.matrix_version();
                if now != **version {
                    columns.iter_mut().for_each(|c| *c = None);
                    **version = now;
                }
                needed.retain(|&v| row_of[v] != u32::MAX);
                needed.sort_unstable();
                needed.dedup();
                needed.retain(|&v| columns[v].is_none());
                let n = solve.solution_mut().len();
                let mut cols = vec![0.0; n * COLUMN_BATCH.min(needed.len())];
                for chunk in needed.chunks(COLUMN_BATCH) {
                    let cols = &mut cols[..n * chunk.len()];
                    cols.fill(0.0);
                    for (c, &v) in chunk.iter().enumerate() {
                        cols[c * n + row_of[v] as usize] = 1.0;
                    }
                    solve.solve_columns(cols, chunk.len());
                    for (c, &v) in chunk.iter().enumerate() {
                        columns[v] = Some(cols[c * n..(c + 1) * n].into());
                    }
                }
            },
        );
    }

    /// The entries `(body, vertex, coefficient)` of row `r`'s vector `a_r` on free vertices.
    fn entries(&self, r: usize) -> impl Iterator<Item = (usize, usize, f64)> + '_ {
        let row = &self.rows[r];
        let p = &row.pair;
        let sides = if row.obstacle.is_some() { 0 } else { 3 };
        std::iter::once((p.body, p.vertex, 1.0)).chain(
            (0..sides)
                .map(move |t| (p.other, p.triangle[t], -p.weights[t]))
                .filter(move |&(k, v, _)| self.row_of[k][v] != u32::MAX),
        )
    }

    /// The rows in blocks that do not couple, each with its scalar coupling `G_rc = a_r . A^{-1} a_c` (local,
    /// row-major): a unit force along `d` on row `c` moves row `r`'s point along `d'` by `(d . d') G_rc` (the
    /// matrix is the same for x, y and z). Rows couple when they have entries on a common body that is not
    /// frozen (its `A^{-1}` is dense), so a block is the rows of bodies that touch, directly or through others:
    /// bodies landing apart on the floor are blocks of their own, whose active sets are solved apart (the
    /// cost is cubic in the rows solved together: one pile step of 14 rounds of 345 rows, 9 ms, became one of
    /// eight blocks of about 45). Summed body by body over the pairs of the rows' entries on it, from the
    /// column of `c`'s vertex at `r`'s (a frozen body's side does not move: no entries).
    fn blocks(&self) -> Vec<Block> {
        let nr = self.rows.len();
        let nb = self.row_of.len();
        let mut on: Vec<Vec<(usize, usize, f64)>> = vec![Vec::new(); nb];
        for r in 0..nr {
            for (k, v, coef) in self.entries(r) {
                if !self.frozen[k] {
                    on[k].push((r, v, coef));
                }
            }
        }
        // Union-find over the rows (a dozen lines, not worth a graph crate): all the rows with an entry on a
        // body are joined.
        let mut parent: Vec<usize> = (0..nr).collect();
        fn root(parent: &mut [usize], mut r: usize) -> usize {
            while parent[r] != r {
                parent[r] = parent[parent[r]];
                r = parent[r];
            }
            r
        }
        for entries in &on {
            if let Some(&(first, ..)) = entries.first() {
                for &(r, ..) in &entries[1..] {
                    let (a, b) = (root(&mut parent, first), root(&mut parent, r));
                    parent[a.max(b)] = a.min(b);
                }
            }
        }
        // Blocks in the order of their first rows, rows in ascending order within each.
        let mut block_of = vec![usize::MAX; nr];
        let mut local = vec![0; nr];
        let mut blocks: Vec<Block> = Vec::new();
        for r in 0..nr {
            let top = root(&mut parent, r);
            if block_of[top] == usize::MAX {
                block_of[top] = blocks.len();
                blocks.push(Block::default());
            }
            let b = block_of[top];
            block_of[r] = b;
            local[r] = blocks[b].rows.len();
            blocks[b].rows.push(r);
        }
        for block in &mut blocks {
            let n = block.rows.len();
            block.coupling = vec![0.0; n * n];
        }
        for (k, entries) in on.iter().enumerate() {
            let Some(&(first, ..)) = entries.first() else {
                continue;
            };
            let block = &mut blocks[block_of[first]];
            let n = block.rows.len();
            let row_of = &self.row_of[k];
            for &(c, v, cb) in entries {
                let col = self.columns[k][v].as_ref().expect("solved");
                for &(r, u, ca) in entries {
                    if r >= c {
                        block.coupling[local[r] * n + local[c]] +=
                            ca * cb * col[row_of[u] as usize];
                    }
                }
            }
        }
        for block in &mut blocks {
            let n = block.rows.len();
            for r in 0..n {
                for c in 0..r {
                    block.coupling[c * n + r] = block.coupling[r * n + c];
                }
            }
        }
        blocks
    }

    /// The row's stiffness `k = ROW_STIFFNESS_RATIO / (h^2 K)`, N/m.
    fn stiffness(&self, r: usize) -> f64 {
        ROW_STIFFNESS_RATIO / (self.h * self.h * self.rows[r].pair.inverse_mass)
    }

    /// Correct the bodies' solutions of this iteration (after the `solve` of every body not `done`) so that no
    /// row ends with a negative gap, by the active-set Woodbury solve of the module comment, block by block
    /// ([`Self::blocks`]). A body done iterating stays at its iterate (its side of a row does not move).
    pub(super) fn correct(&mut self, sims: &mut [&mut Simulation], done: &[bool]) {
        self.frozen = done.to_vec();
        self.follow(sims);
        let nr = self.rows.len();
        if nr == 0 {
            return;
        }
        self.solve_columns(sims);
        // The rows' gaps in the unconstrained solutions (pinned vertices and frozen bodies stay put).
        // Read in place: a pinned vertex or a body done iterating stays at its iterate.
        let row_of = &self.row_of;
        let at = |sims: &mut [&mut Simulation], k: usize, v: usize| {
            let q = row_of[k][v];
            if q == u32::MAX || done[k] {
                coupled(sims[k]).positions()[v]
            } else {
                coupled(sims[k]).solution_mut()[q as usize]
            }
        };
        // Each row's vertex relative to its point on the other side, in the unconstrained solutions and at the
        // start of the step (an obstacle's point where the obstacle's motion had it then).
        let relative: Vec<(Vec3, Vec3)> = self
            .rows
            .iter()
            .map(|row| {
                let p = &row.pair;
                let (q, q0) = if let Some(o) = row.obstacle {
                    (
                        p.point,
                        sims[p.body].world.obstacles[o].point_at_start(p.point),
                    )
                } else {
                    (0..3).fold(([0.0; 3], [0.0; 3]), |(q, q0), t| {
                        let start = sims[p.other].state.x[p.triangle[t]];
                        (
                            add(q, scale(at(sims, p.other, p.triangle[t]), p.weights[t])),
                            add(q0, scale(start, p.weights[t])),
                        )
                    })
                };
                (
                    sub(at(sims, p.body, p.vertex), q),
                    sub(sims[p.body].state.x[p.vertex], q0),
                )
            })
            .collect();
        // The friction of the last iteration, in each row's current tangent plane, is where the friction solve
        // below starts: the normal forces are solved with it in place.
        for row in self.rows.iter_mut() {
            let n = row.pair.normal;
            row.friction = sub(row.friction, scale(n, dot(n, row.friction)));
        }
        let mu: Vec<f64> = (0..nr).map(|r| self.friction_of(sims, r)).collect();
        let blocks = self.blocks();
        for block in blocks {
            self.solve_block(&block, &relative, &mu);
        }
        // x = y + sum_r mu_r (A^{-1} a_r) n_r, body by body (at once), column by column.
        let mut pushes: Vec<Vec<(usize, Vec3)>> = vec![Vec::new(); sims.len()];
        for r in 0..nr {
            if self.rows[r].force == 0.0 {
                continue;
            }
            let force = self.row_force(r);
            for (b, v, coef) in self.entries(r) {
                if !done[b] {
                    pushes[b].push((v, scale(force, coef)));
                }
            }
        }
        let mut bodies: Vec<_> = sims.iter_mut().map(|s| &mut **s).zip(pushes).collect();
        let columns = &self.columns;
        crate::exec::for_each_mut(&mut bodies, |k, (sim, pushes)| {
            let out = coupled(sim).solution_mut();
            for &(v, d) in pushes.iter() {
                let col = columns[k][v].as_ref().expect("solved");
                for (o, &z) in out.iter_mut().zip(col.iter()) {
                    *o = add(*o, scale(d, z));
                }
            }
        });
    }

    /// The forces of one block's rows: their normal forces by the active-set rounds (solve the active rows, drop
    /// pulling ones, add those that would end negative), then their friction ([`Self::add_friction`]).
    /// `relative`: every row's vertex relative to its point, in the unconstrained solutions and at the start;
    /// `mu`: every row's friction coefficient.
    fn solve_block(&mut self, block: &Block, relative: &[(Vec3, Vec3)], mu: &[f64]) {
        let rows = &block.rows;
        let n = rows.len();
        let g = &block.coupling;
        // The rows' normals and last friction, local (read n^2 times below).
        let normals: Vec<Vec3> = rows.iter().map(|&r| self.rows[r].pair.normal).collect();
        let rubbing: Vec<(usize, Vec3)> = rows
            .iter()
            .enumerate()
            .map(|(b, &r)| (b, self.rows[r].friction))
            .filter(|&(_, f)| f != [0.0; 3])
            .collect();
        // The gaps with the friction of the last iteration applied.
        let gaps: Vec<f64> = (0..n)
            .map(|a| {
                let from_friction: f64 = rubbing
                    .iter()
                    .map(|&(b, f)| dot(normals[a], f) * g[a * n + b])
                    .sum();
                dot(normals[a], relative[rows[a]].0) + from_friction
            })
            .collect();
        let mut delassus = vec![0.0; n * n];
        for (a, (out, g)) in delassus
            .chunks_exact_mut(n)
            .zip(g.chunks_exact(n))
            .enumerate()
        {
            for ((d, &gab), nb) in out.iter_mut().zip(g).zip(&normals) {
                if gab != 0.0 {
                    *d = dot(normals[a], *nb) * gab;
                }
            }
        }
        // The active set starts from the last iteration's (rows then pushing) and the rows now negative.
        let mut active: Vec<bool> = (0..n)
            .map(|a| gaps[a] < 0.0 || self.rows[rows[a]].force > 0.0)
            .collect();
        let mut force = vec![0.0; n];
        for _ in 0..ACTIVE_SET_ROUNDS {
            let set: Vec<usize> = (0..n).filter(|&a| active[a]).collect();
            force.iter_mut().for_each(|f| *f = 0.0);
            if !set.is_empty() {
                let na = set.len();
                let mut c = if na == n {
                    delassus.clone()
                } else {
                    let mut c = vec![0.0; na * na];
                    for (out, &a) in c.chunks_exact_mut(na).zip(&set) {
                        let from = &delassus[a * n..(a + 1) * n];
                        for (o, &b) in out.iter_mut().zip(&set) {
                            *o = from[b];
                        }
                    }
                    c
                };
                for (i, &a) in set.iter().enumerate() {
                    c[i * na + i] += 1.0 / self.stiffness(rows[a]);
                }
                let rhs: Vec<f64> = set.iter().map(|&a| -gaps[a]).collect();
                let sol = solve_positive_definite(&c, na, &rhs);
                for (i, &a) in set.iter().enumerate() {
                    force[a] = sol[i];
                }
            }
            let pushing: Vec<usize> = (0..n).filter(|&b| force[b] > 0.0).collect();
            let mut changed = false;
            for a in 0..n {
                if active[a] && force[a] < 0.0 {
                    active[a] = false;
                    changed = true;
                } else if !active[a] {
                    let from = &delassus[a * n..(a + 1) * n];
                    let moved: f64 = pushing.iter().map(|&b| from[b] * force[b]).sum();
                    if gaps[a] + moved < 0.0 {
                        active[a] = true;
                        changed = true;
                    }
                }
            }
            if !changed {
                break;
            }
        }
        for a in 0..n {
            self.rows[rows[a]].force = if active[a] { force[a].max(0.0) } else { 0.0 };
        }
        let slips: Vec<Vec3> = rows
            .iter()
            .map(|&r| sub(relative[r].0, relative[r].1))
            .collect();
        self.add_friction(block, &slips, mu);
    }

    /// Row `r`'s force vector (N): its normal force along the normal plus its friction.
    fn row_force(&self, r: usize) -> Vec3 {
        let row = &self.rows[r];
        add(scale(row.pair.normal, row.force), row.friction)
    }

    /// Row `r`'s Coulomb friction coefficient: the obstacle's, or the geometric mean of the two bodies'.
    fn friction_of(&self, sims: &[&mut Simulation], r: usize) -> f64 {
        let p = &self.rows[r].pair;
        match self.rows[r].obstacle {
            Some(o) => sims[p.body].world.obstacles[o].friction,
            None => (self.friction[p.body] * self.friction[p.other]).sqrt(),
        }
    }

    /// Coulomb friction on a block's rows that push (`force > 0`, set by the normal solve): each row's friction
    /// force `f` (in the tangent plane of its normal) aims at no sliding over the step (the vertex's displacement
    /// relative to its point on the other side, `slips` in the unconstrained solutions, plus what every row's
    /// force adds through the block's coupling, has no tangential part), within the cone `|f| <= mu f_n`.
    /// Solved by projected Gauss-Seidel sweeps over the rows in order, starting from the last iteration's forces
    /// (the iterations of the step continue it): a joint dense solve of two tangents per row is too costly for
    /// a pile's hundreds of rows. Equal and opposite on both sides, like the normal force.
    fn add_friction(&mut self, block: &Block, slips: &[Vec3], mu: &[f64]) {
        let rows = &block.rows;
        let n = rows.len();
        let g = &block.coupling;
        let rubbing = |s: &Self, a: usize| s.rows[rows[a]].force > 0.0 && mu[rows[a]] > 0.0;
        let sweep: Vec<usize> = (0..n).filter(|&a| rubbing(self, a)).collect();
        for a in 0..n {
            if !rubbing(self, a) {
                self.rows[rows[a]].friction = [0.0; 3];
            }
        }
        if sweep.is_empty() {
            return;
        }
        let tangential = |n: Vec3, v: Vec3| sub(v, scale(n, dot(n, v)));
        // The start: last iteration's friction, in the current tangent plane and cone.
        for &a in &sweep {
            let row = &self.rows[rows[a]];
            let f = tangential(row.pair.normal, row.friction);
            self.rows[rows[a]].friction = clamp_length(f, mu[rows[a]] * row.force);
        }
        // Every row's displacement relative to its point, with all the block's forces.
        let force: Vec<Vec3> = rows.iter().map(|&r| self.row_force(r)).collect();
        let mut moved: Vec<Vec3> = (0..n)
            .map(|a| (0..n).fold(slips[a], |s, b| add(s, scale(force[b], g[a * n + b]))))
            .collect();
        for _ in 0..FRICTION_SWEEPS {
            for &a in &sweep {
                let r = rows[a];
                let row = &self.rows[r];
                let normal = row.pair.normal;
                let slip = tangential(normal, moved[a]);
                let f_old = row.friction;
                let step = scale(slip, -1.0 / (g[a * n + a] + 1.0 / self.stiffness(r)));
                let f_new = clamp_length(add(f_old, step), mu[r] * row.force);
                let change = sub(f_new, f_old);
                if change == [0.0; 3] {
                    continue;
                }
                self.rows[r].friction = f_new;
                for (b, m) in moved.iter_mut().enumerate() {
                    *m = add(*m, scale(change, g[b * n + a]));
                }
            }
        }
    }

    /// Speeds below this are resting contact (m/s): [`RESTING_SPEED_STEPS`] steps of `sim`'s gravity.
    fn resting_speed(&self, sim: &Simulation) -> f64 {
        RESTING_SPEED_STEPS * norm(sim.model.gravity) * self.h
    }

    /// A vertex's mean velocity over the part, `(v_start + v_end) / 2` (m/s): an impulse `J` changing a mass's
    /// velocity does the work `J . (v_start + v_end) / 2` on it.
    fn mean_velocity(&self, sims: &[&mut Simulation], k: usize, v: usize) -> Vec3 {
        scale(add(self.v_start[k][v], sims[k].state.v[v]), 0.5)
    }

    /// What the rows exchanged over the step `h`, per body, from their forces of the last iteration, at the
    /// bodies' end-of-step states: the impulse `h mu n` on the vertex and `-h mu w_j n` on the corners (the
    /// part on free corners), both moments taken at the point `sum_j w_j x_j` so that they cancel; each side's
    /// work at its point: on a row whose pair approached or separated faster than the resting speed at the
    /// start of the step (an impact, its rebound) the normal impulse's `J . (v_start + v_end) / 2`, the kinetic
    /// energy it changes; on a resting row `J . v_end`, the force's work over the step's displacement (a
    /// positional step moves the vertex by `h v_end`), as the potentials' change is measured. Why not the mean
    /// velocity at rest too: on a block rocking on a slab it books positive work step after step (+4.2 J in 5 s
    /// against 0.9 J of damping), which FEPR would put back as vibration: the block would never come to rest.
    /// For an impact (a pair of bodies
    /// whose rows approached faster than the resting speed), the share `e^2` of what the pair lost is given
    /// back in proportion to the bodies' inverse masses (the bounce is the projections', as for obstacles).
    pub(super) fn exchanges(
        &self,
        sims: &[&mut Simulation],
        coefficients: &[BodyCoefficients],
    ) -> Vec<BodyExchange> {
        let nb = sims.len();
        let h = self.h;
        let mut out = vec![BodyExchange::default(); nb];
        let mut work = vec![vec![0.0; nb]; nb];
        let mut approach = vec![vec![0.0f64; nb]; nb];
        let mut normal_loss = vec![vec![0.0; nb]; nb];
        for (r, row) in self.rows.iter().enumerate() {
            let p = &row.pair;
            if let Some(o) = row.obstacle {
                // An obstacle's row: an external impulse at the surface point; an impact's loss is booked with
                // the share e^2 given back (the projections' bounce, as for the obstacles' own contacts).
                if row.force == 0.0 {
                    continue;
                }
                let sim = &sims[p.body];
                let j = scale(self.row_force(r), h);
                let resting_speed = self.resting_speed(sim);
                let impact = -row.approach_speed > resting_speed;
                let v = if row.approach_speed.abs() <= resting_speed {
                    sim.state.v[p.vertex]
                } else {
                    self.mean_velocity(sims, p.body, p.vertex)
                };
                let wn = h * row.force * dot(p.normal, v);
                // Friction's work over the step's displacement (see the rows between bodies below).
                let w = wn
                    + dot(
                        sub(j, scale(p.normal, h * row.force)),
                        sim.state.v[p.vertex],
                    );
                // The share an impact's restitution gives back, of the normal work relative to the obstacle's
                // surface (a moving obstacle's own work on the vertex stays booked in full).
                let ob = &sim.world.obstacles[o];
                let wn_relative = wn - h * row.force * dot(p.normal, ob.velocity_at(p.point));
                let w = if impact && wn_relative < 0.0 {
                    w - ob.restitution * ob.restitution * wn_relative
                } else {
                    w
                };
                let e = &mut out[p.body];
                e.contacts += 1;
                e.impulse = add(e.impulse, j);
                e.moment = add(e.moment, cross(p.point, j));
                e.vertices.push(p.vertex as u32);
                e.work += w;
                continue;
            }
            let (a, b) = (p.body, p.other);
            approach[a][b] = approach[a][b].max(-row.approach_speed);
            approach[b][a] = approach[a][b];
            if row.force == 0.0 {
                continue;
            }
            let j = scale(self.row_force(r), h);
            let jn = scale(p.normal, h * row.force);
            let xb = &sims[b].state.x;
            let point = (0..3).fold([0.0; 3], |s, t| {
                add(s, scale(xb[p.triangle[t]], p.weights[t]))
            });
            let free_share: f64 = (0..3)
                .filter(|&t| !sims[b].model.pinned[p.triangle[t]])
                .map(|t| p.weights[t])
                .sum();
            let jb = scale(j, -free_share);
            // Each side's work: the normal impulse's at the mean velocity over the step on an impact (the kinetic
            // energy an impulse changes), at the end velocity at rest (below); friction's as the force's work over
            // the displacement of the step, `J_t . v_end` (positional steps: `v_end = dx / h`), so that the pair's
            // is `-f . slip`, never positive (sticking: zero). The normal part's sum is what an impact's
            // restitution gives a share of back.
            let jt = sub(j, jn);
            let on_b = |f: Vec3, end: bool| -> f64 {
                (0..3)
                    .filter(|&t| !sims[b].model.pinned[p.triangle[t]])
                    .map(|t| {
                        let v = if end {
                            sims[b].state.v[p.triangle[t]]
                        } else {
                            self.mean_velocity(sims, b, p.triangle[t])
                        };
                        p.weights[t] * dot(f, v)
                    })
                    .sum::<f64>()
            };
            let resting = row.approach_speed.abs() <= self.resting_speed(sims[a]);
            let va = if resting {
                sims[a].state.v[p.vertex]
            } else {
                self.mean_velocity(sims, a, p.vertex)
            };
            let normal = (dot(jn, va), -on_b(jn, resting));
            work[a][b] += normal.0 + dot(jt, sims[a].state.v[p.vertex]);
            work[b][a] += normal.1 - on_b(jt, true);
            normal_loss[a][b] += normal.0 + normal.1;
            for (k, got, verts) in [(a, j, &[p.vertex][..]), (b, jb, &p.triangle[..])] {
                let e = &mut out[k];
                e.max_approach = e.max_approach.max(-row.approach_speed);
                e.contacts += 1;
                e.impulse = add(e.impulse, got);
                e.moment = add(e.moment, cross(point, got));
                e.vertices.extend(verts.iter().map(|&v| v as u32));
            }
        }
        // Each body's centre-of-mass velocity at the start of the step (m/s): the mass-weighted mean of its
        // velocities, as of its positions.
        let centre_velocity: Vec<Vec3> = sims
            .iter()
            .zip(&self.v_start)
            .map(|(sim, v)| center_of_mass(&sim.model.masses, sim.model.total_mass, v))
            .collect();
        for a in 0..nb {
            for b in a + 1..nb {
                let (mut wa, mut wb) = (work[a][b], work[b][a]);
                // Shares of the pair's corrections, in proportion to the bodies' inverse masses.
                let (ia, ib) = (
                    1.0 / sims[a].model.total_mass,
                    1.0 / sims[b].model.total_mass,
                );
                let (share_a, share_b) = (ia / (ia + ib), ib / (ia + ib));
                let loss = normal_loss[a][b] + normal_loss[b][a];
                let resting_speed = self.resting_speed(sims[a]);
                if approach[a][b] > resting_speed && loss < 0.0 {
                    let e = coefficients[a].restitution.min(coefficients[b].restitution);
                    let back = -e * e * loss;
                    wa += back * share_a;
                    wb += back * share_b;
                }
                // A collision's rebound: the rows push while the pair separates, and the sides' normal work sums
                // to more than zero. That is the compressed bodies' elastic energy coming back, already in their
                // energy, not work the contact does (a passive constraint never gives the pair energy): booked,
                // it would make two bodies colliding with restitution 1 gain 8% of their energy (Projective
                // Dynamics, 1/240), 85% without the quality guard (1/60). So while the bodies move against each
                // other (their centres of mass faster than the resting speed), the gain is taken out of both
                // sides' work, in proportion to their inverse masses. Bodies at rest on each other keep their
                // sides' work over the displacement (taken out there too, the pile's resting bodies fail 1 in 5
                // projections instead of 1 in 8, and keep 10 times the kinetic energy).
                let relative = norm(sub(centre_velocity[a], centre_velocity[b]));
                if loss > 0.0 && relative > resting_speed {
                    wa -= loss * share_a;
                    wb -= loss * share_b;
                }
                out[a].work += wa;
                out[b].work += wb;
            }
        }
        for e in &mut out {
            e.vertices.sort_unstable();
            e.vertices.dedup();
            e.held = e.contacts > 0;
        }
        out
    }
}

/// Rounds of the active-set solve per iteration (each a dense factorisation of the active rows).
const ACTIVE_SET_ROUNDS: usize = 8;

/// Projected Gauss-Seidel sweeps of the friction per iteration (continued by the next iteration).
const FRICTION_SWEEPS: usize = 3;

/// `v` shortened to at most `bound` long.
fn clamp_length(v: Vec3, bound: f64) -> Vec3 {
    let len = norm(v);
    if len > bound {
        scale(v, bound.max(0.0) / len)
    } else {
        v
    }
}

/// Columns `A^{-1} e_v` solved together: one pass over the factor serves them all (the pile's columns, solved
/// three at a time, took 4-10 ms of a 60 ms step).
const COLUMN_BATCH: usize = 32;

/// Rows a vertex may have against one other body (the faces of a crease it sits in).
const ROWS_PER_VERTEX: usize = 3;

/// A row's stiffness over its pair's effective mass per step squared: its force `mu` leaves the gap at
/// `-mu h^2 K / ROW_STIFFNESS_RATIO` (micrometres in the pile). Stiffer than the obstacles' constraints
/// ([`crate::world::STIFFNESS_RATIO`], in the matrix, where it slows the iterations): a row is solved exactly, and only
/// keeps the active rows' system positive definite.
const ROW_STIFFNESS_RATIO: f64 = 1e5;

/// Solve the dense symmetric positive definite system `c x = rhs` (`c` `n` x `n`, exactly symmetric: read as
/// row-major or column-major alike): faer's blocked
/// Cholesky factorisation, sequential (the same bits for any thread count); the least-squares fallback of
/// [`crate::math::solve_symmetric_psd`] should rounding make it indefinite.
pub(super) fn solve_positive_definite(c: &[f64], n: usize, rhs: &[f64]) -> Vec<f64> {
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::cholesky::llt::factor::{cholesky_in_place, cholesky_in_place_scratch};
    use faer::linalg::triangular_solve::{
        solve_lower_triangular_in_place, solve_upper_triangular_in_place,
    };
    use faer::{Mat, Par};
    // Filled column by column from slices (faer's `from_fn` costs more than the factorisation at n = 400).
    let mut l = Mat::<f64>::zeros(n, n);
    for j in 0..n {
        l.col_mut(j)
            .try_as_col_major_mut()
            .expect("a fresh matrix is column-major")
            .as_slice_mut()
            .copy_from_slice(&c[j * n..(j + 1) * n]);
    }
    let mut mem = MemBuffer::new(cholesky_in_place_scratch::<f64>(
        n,
        Par::Seq,
        Default::default(),
    ));
    let factored = cholesky_in_place(
        l.as_mut(),
        Default::default(),
        Par::Seq,
        MemStack::new(&mut mem),
        Default::default(),
    );
    if factored.is_err() {
        return crate::math::solve_symmetric_psd(c, rhs, n, 0.0).0;
    }
    let mut x = Mat::<f64>::from_fn(n, 1, |i, _| rhs[i]);
    solve_lower_triangular_in_place(l.as_ref(), x.as_mut(), Par::Seq);
    solve_upper_triangular_in_place(l.as_ref().transpose(), x.as_mut(), Par::Seq);
    (0..n).map(|i| x[(i, 0)]).collect()
}

/// Vertices inside an obstacle by less than this share of the impact limit are left to the obstacle's own
/// constraint in the body's matrix (resting on the floor, they sink that much under the pile's weight).
const SHALLOW: f64 = 0.1;

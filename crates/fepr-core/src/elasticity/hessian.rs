//! Element and global Hessians of the elastic energy.
//!
//! Element Hessian of `V Psi(F(x))` (12 x 12): with `g_a` the gradient of the linear shape function of
//! vertex `a` (`g_1..g_3` = rows of `D_m^-1`, `g_0 = -(g_1 + g_2 + g_3)`), `dF_ij/dx_{a,i} = g_a[j]` and
//! `H[3a+i][3b+k] = V sum_{j,l} g_a[j] (dP/dF)[3i+j][3k+l] g_b[l]`. Projected to positive semi-definite by
//! clamping the negative eigenvalues of the 9 x 9 `dP/dF` (then `H = V B^T (dP/dF)+ B` is PSD too).
//!
//! Global assembly goes into a fixed lower-triangle pattern over the free (unpinned) degrees of freedom;
//! per-tet scatter positions are computed once, element matrices are computed in parallel and scattered in
//! tet order (deterministic).

use crate::elasticity::deformation_gradient;
use crate::material::Hyperelastic;
use crate::math::LowerPattern;
use crate::math::{Mat3, Vec3};
use crate::model::Model;

/// A 12 x 12 element matrix, row-major, index `3 * corner + axis`.
pub type ElementMatrix = [f64; 144];

/// Shape-function gradients `g_0..g_3` of tet `e` in its rest configuration (`dF/dx_a = g_a`).
pub fn shape_gradients(model: &Model, e: usize) -> [Vec3; 4] {
    let d = &model.dm_inv(e);
    let g1 = d[0];
    let g2 = d[1];
    let g3 = d[2];
    [
        [
            -(g1[0] + g2[0] + g3[0]),
            -(g1[1] + g2[1] + g3[1]),
            -(g1[2] + g2[2] + g3[2]),
        ],
        g1,
        g2,
        g3,
    ]
}

/// Element Hessian of tet `e` at positions `x`; `psd` projects `dP/dF` to positive semi-definite first.
pub fn element_hessian(model: &Model, x: &[Vec3], e: usize, psd: bool) -> ElementMatrix {
    let f = deformation_gradient(model, x, e);
    let d = if psd {
        model.material.stress_derivative_psd(&f)
    } else {
        model.material.stress_derivative(&f)
    };
    let g = shape_gradients(model, e);
    let vol = model.rest_volume[e];
    // t[3i+j][3b+k] = sum_l D[3i+j][3k+l] g_b[l]
    let mut t = [[0.0; 12]; 9];
    for r in 0..9 {
        for b in 0..4 {
            for k in 0..3 {
                let mut s = 0.0;
                for l in 0..3 {
                    s += d[r][3 * k + l] * g[b][l];
                }
                t[r][3 * b + k] = s;
            }
        }
    }
    let mut h = [0.0; 144];
    for a in 0..4 {
        for i in 0..3 {
            for c in 0..12 {
                let mut s = 0.0;
                for j in 0..3 {
                    s += g[a][j] * t[3 * i + j][c];
                }
                h[(3 * a + i) * 12 + c] = vol * s;
            }
        }
    }
    h
}

/// Assembles `mass_scale * M + sum_e H_e` over the free degrees of freedom into a fixed pattern.
#[derive(Clone, Debug)]
pub struct HessianAssembler {
    /// Lower-triangle pattern over free dofs (`3 * free_vertex + axis`).
    pub pattern: LowerPattern,
    /// Free index of each vertex (`usize::MAX` for pinned ones).
    pub free_index: Vec<usize>,
    /// For each tet, the 144 value positions of its entries (`u32::MAX`: pinned or upper triangle).
    scatter: Vec<u32>,
    /// Value position of each free dof's diagonal entry.
    diagonal: Vec<usize>,
    elements: Vec<ElementMatrix>,
}

impl HessianAssembler {
    pub fn new(model: &Model) -> Self {
        let m = model.num_vertices();
        let mut free_index = vec![usize::MAX; m];
        let mut nfree = 0;
        for i in 0..m {
            if !model.pinned[i] {
                free_index[i] = nfree;
                nfree += 1;
            }
        }
        let n = 3 * nfree;
        let dof = |v: usize, a: usize| (free_index[v] != usize::MAX).then(|| 3 * free_index[v] + a);
        let mut columns: Vec<Vec<usize>> = vec![Vec::new(); n];
        for t in model.mesh.tets() {
            for &p in t {
                for &q in t {
                    for a in 0..3 {
                        for b in 0..3 {
                            if let (Some(r), Some(c)) = (dof(p, a), dof(q, b)) {
                                if r >= c {
                                    columns[c].push(r);
                                }
                            }
                        }
                    }
                }
            }
        }
        let pattern = LowerPattern::from_columns(n, columns);
        let mut scatter = Vec::with_capacity(144 * model.num_tets());
        for t in model.mesh.tets() {
            for a in 0..4 {
                for i in 0..3 {
                    for b in 0..4 {
                        for k in 0..3 {
                            let pos = match (dof(t[a], i), dof(t[b], k)) {
                                (Some(r), Some(c)) if r >= c => {
                                    pattern.position(r, c).expect("entry in pattern") as u32
                                }
                                _ => u32::MAX,
                            };
                            scatter.push(pos);
                        }
                    }
                }
            }
        }
        let diagonal = (0..n)
            .map(|c| pattern.position(c, c).expect("diagonal in pattern"))
            .collect();
        Self {
            pattern,
            free_index,
            scatter,
            diagonal,
            elements: Vec::new(),
        }
    }

    /// Number of free degrees of freedom.
    pub fn ndof(&self) -> usize {
        self.pattern.n
    }

    /// `values <- mass_scale * M + sum_e H_e(x)` (lower triangle, free dofs).
    pub fn assemble(
        &mut self,
        model: &Model,
        x: &[Vec3],
        mass_scale: f64,
        psd: bool,
        values: &mut Vec<f64>,
    ) {
        values.clear();
        values.resize(self.pattern.nnz(), 0.0);
        self.elements.resize(model.num_tets(), [0.0; 144]);
        // Fixed chunks of elements ([`crate::exec::for_each_chunk_mut`], so that `parallel::serial` holds).
        const ELEMENTS: usize = 64;
        crate::exec::for_each_chunk_mut(&mut self.elements, ELEMENTS, |c, hs| {
            for (k, h) in hs.iter_mut().enumerate() {
                *h = element_hessian(model, x, c * ELEMENTS + k, psd);
            }
        });
        for (e, h) in self.elements.iter().enumerate() {
            let positions = &self.scatter[144 * e..144 * (e + 1)];
            for (k, &pos) in positions.iter().enumerate() {
                if pos != u32::MAX {
                    values[pos as usize] += h[k];
                }
            }
        }
        for (i, &fi) in self.free_index.iter().enumerate() {
            if fi == usize::MAX {
                continue;
            }
            for a in 0..3 {
                values[self.diagonal[3 * fi + a]] += mass_scale * model.masses[i];
            }
        }
    }

    /// `values += block` on the diagonal block of vertex `i` (a symmetric 3x3 matrix; its lower triangle is
    /// read). Nothing for a pinned vertex. For terms that act on one vertex alone (contact penalties).
    pub fn add_vertex_block(&self, values: &mut [f64], i: usize, block: &Mat3) {
        let fi = self.free_index[i];
        if fi == usize::MAX {
            return;
        }
        for a in 0..3 {
            for b in 0..=a {
                let pos = if a == b {
                    self.diagonal[3 * fi + a]
                } else {
                    self.pattern
                        .position(3 * fi + a, 3 * fi + b)
                        .expect("a vertex's own block is in the pattern")
                };
                values[pos] += block[a][b];
            }
        }
    }

    /// `y = A x` for the assembled lower-triangle values (free dofs), for tests and residual checks.
    pub fn multiply(&self, values: &[f64], x: &[f64]) -> Vec<f64> {
        let p = &self.pattern;
        let mut y = vec![0.0; p.n];
        for c in 0..p.n {
            for k in p.col_ptr[c]..p.col_ptr[c + 1] {
                let r = p.row_idx[k];
                y[r] += values[k] * x[c];
                if r != c {
                    y[c] += values[k] * x[r];
                }
            }
        }
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::elasticity::{elastic_energy_gradient, ElasticWorkspace};
    use crate::material::{Material, NeoHookean, StableNeoHookean};
    use crate::math::symmetric_eigen;
    use crate::mesh::{tests::cube, MassSpec, TetMesh};
    use crate::model::ModelBuilder;

    fn model(material: Material, pinned: Vec<usize>) -> Model {
        let (v, t) = cube();
        let (mesh, _) = TetMesh::new(v, &t).unwrap();
        ModelBuilder::new(mesh, material)
            .mass(MassSpec::NodeMass(0.5))
            .pinned(pinned)
            .build()
            .unwrap()
    }

    fn deformed(model: &Model) -> Vec<Vec3> {
        model
            .mesh
            .vertices()
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let k = i as f64;
                [
                    1.2 * p[0] + 0.05 * k.sin(),
                    0.9 * p[1] + 0.1 * p[2],
                    1.05 * p[2] - 0.04 * k.cos(),
                ]
            })
            .collect()
    }

    fn gradient(model: &Model, x: &[Vec3]) -> Vec<Vec3> {
        let mut g = vec![[0.0; 3]; x.len()];
        elastic_energy_gradient(model, x, &mut ElasticWorkspace::default(), &mut g);
        g
    }

    #[test]
    fn global_hessian_matches_finite_differences_of_the_gradient() {
        for mat in [
            Material::NeoHookean(NeoHookean::new(1e3, 0.3).unwrap()),
            Material::StableNeoHookean(StableNeoHookean::new(1e3, 0.4).unwrap()),
        ] {
            for pinned in [vec![], vec![0, 5]] {
                let m = model(mat, pinned);
                let x = deformed(&m);
                let mut asm = HessianAssembler::new(&m);
                let mut values = Vec::new();
                asm.assemble(&m, &x, 0.0, false, &mut values);
                let n = asm.ndof();
                let scale = values.iter().fold(0.0f64, |a, b| a.max(b.abs()));
                // Column by column: H e_c against (grad(x + h e_c) - grad(x - h e_c)) / 2h on free rows.
                for (vi, &fi) in asm.free_index.iter().enumerate() {
                    if fi == usize::MAX {
                        continue;
                    }
                    for a in 0..3 {
                        let c = 3 * fi + a;
                        let mut unit = vec![0.0; n];
                        unit[c] = 1.0;
                        let col = asm.multiply(&values, &unit);
                        let h = 1e-6;
                        let mut xp = x.clone();
                        xp[vi][a] += h;
                        let mut xm = x.clone();
                        xm[vi][a] -= h;
                        let (gp, gm) = (gradient(&m, &xp), gradient(&m, &xm));
                        for (vj, &fj) in asm.free_index.iter().enumerate() {
                            if fj == usize::MAX {
                                continue;
                            }
                            for b in 0..3 {
                                let fd = (gp[vj][b] - gm[vj][b]) / (2.0 * h);
                                let an = col[3 * fj + b];
                                assert!(
                                    (fd - an).abs() <= 1e-6 * scale,
                                    "{mat:?} H[{vj},{b}][{vi},{a}]: fd {fd} vs {an}"
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn projected_element_hessians_are_positive_semi_definite_and_exact_when_already_psd() {
        let m = model(
            Material::NeoHookean(NeoHookean::new(1e3, 0.45).unwrap()),
            vec![],
        );
        // A strongly compressed state (indefinite Neo-Hookean Hessian).
        let x: Vec<Vec3> = m
            .mesh
            .vertices()
            .iter()
            .map(|p| [0.3 * p[0], p[1] + 0.4 * p[0], 0.5 * p[2]])
            .collect();
        let mut indefinite = 0;
        for e in 0..m.num_tets() {
            let raw = element_hessian(&m, &x, e, false);
            let psd = element_hessian(&m, &x, e, true);
            let (w_raw, _) = symmetric_eigen(&raw, 12);
            let (w_psd, _) = symmetric_eigen(&psd, 12);
            let scale = w_raw.iter().fold(0.0f64, |a, b| a.max(b.abs()));
            indefinite += w_raw.iter().any(|w| *w < -1e-9 * scale) as usize;
            assert!(
                w_psd.iter().all(|w| *w >= -1e-9 * scale),
                "tet {e}: {w_psd:?}"
            );
        }
        assert!(
            indefinite > 0,
            "the test state should produce indefinite element Hessians"
        );
        // At rest the Hessian is PSD already: projection changes nothing.
        let rest = m.mesh.vertices().to_vec();
        for e in 0..m.num_tets() {
            let a = element_hessian(&m, &rest, e, false);
            let b = element_hessian(&m, &rest, e, true);
            let scale = a.iter().fold(0.0f64, |s, v| s.max(v.abs()));
            for k in 0..144 {
                assert!((a[k] - b[k]).abs() <= 1e-9 * scale);
            }
        }
    }
}

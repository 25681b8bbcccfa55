//! Tetrahedral meshes: validation with precise errors, orientation repair, rest shape and lumped masses.

use crate::error::{invalid, FeprError, Result};
use crate::math::{det, inverse, norm, sub, Mat3, Vec3};

/// A tet is degenerate when `|6 V| <= DEGENERATE_RELATIVE_VOLUME * l_max^3`, with `l_max` its longest edge
/// (a regular tet has `6 V / l^3 = 0.7071`): a scale-invariant test for flat or collinear tets. Slivers of
/// real meshes (quality 1e-3) pass; round-off flat tets (1e-16) do not.
pub const DEGENERATE_RELATIVE_VOLUME: f64 = 1e-10;
/// A tet whose longest edge is below this fraction of the mesh's bounding-box diagonal is degenerate too.
pub const DEGENERATE_RELATIVE_SIZE: f64 = 1e-9;

/// What validation found and repaired.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MeshReport {
    /// Tets that were negatively oriented and got their last two vertices swapped.
    pub flipped: usize,
    /// Vertices that no tet references.
    pub unreferenced: usize,
}

/// A validated tetrahedral mesh: rest positions (m, 3) in metres and positively oriented tets (k, 4).
#[derive(Clone, Debug)]
pub struct TetMesh {
    vertices: Vec<Vec3>,
    tets: Vec<[usize; 4]>,
}

/// Six times the signed volume of tet `t` at the positions `p` (negative: inverted).
pub fn signed_volume6(p: &[Vec3], t: &[usize; 4]) -> f64 {
    det(&edge_matrix(p, t))
}

/// `D = [x1 - x0, x2 - x0, x3 - x0]` (columns are edges).
#[inline]
pub fn edge_matrix(p: &[Vec3], t: &[usize; 4]) -> Mat3 {
    let x0 = p[t[0]];
    let e1 = sub(p[t[1]], x0);
    let e2 = sub(p[t[2]], x0);
    let e3 = sub(p[t[3]], x0);
    [
        [e1[0], e2[0], e3[0]],
        [e1[1], e2[1], e3[1]],
        [e1[2], e2[2], e3[2]],
    ]
}

impl TetMesh {
    /// Validate and build a mesh. Tet indices are given as `i64` so that negative values from user data are
    /// reported, not wrapped. Negatively oriented tets are repaired (last two vertices swapped).
    ///
    /// Errors name the tet and the problem: empty mesh, non-finite coordinate (names the vertex), index out of
    /// range, repeated vertex, zero or near-zero volume.
    pub fn new(vertices: Vec<Vec3>, tets_in: &[[i64; 4]]) -> Result<(Self, MeshReport)> {
        let m = vertices.len();
        if m == 0 {
            return Err(FeprError::Mesh("mesh has no vertices".into()));
        }
        if tets_in.is_empty() {
            return Err(FeprError::Mesh("mesh has no tets".into()));
        }
        for (i, v) in vertices.iter().enumerate() {
            if !v.iter().all(|c| c.is_finite()) {
                return Err(FeprError::Mesh(format!(
                    "vertex {i} has a non-finite coordinate {v:?}"
                )));
            }
        }
        let mut lo = vertices[0];
        let mut hi = vertices[0];
        for v in &vertices {
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
        }
        let diag = norm(sub(hi, lo));
        let mut tets = Vec::with_capacity(tets_in.len());
        let mut report = MeshReport::default();
        let mut referenced = vec![false; m];
        for (e, t) in tets_in.iter().enumerate() {
            let mut u = [0usize; 4];
            for c in 0..4 {
                if t[c] < 0 || t[c] as u64 >= m as u64 {
                    return Err(FeprError::Mesh(format!(
                        "tet {e} refers to vertex {} (corner {c}), out of range: the mesh has {m} vertices (0..{})",
                        t[c],
                        m - 1
                    )));
                }
                u[c] = t[c] as usize;
            }
            for a in 0..4 {
                for b in (a + 1)..4 {
                    if u[a] == u[b] {
                        return Err(FeprError::Mesh(format!(
                            "tet {e} repeats vertex {} ({:?})",
                            u[a], t
                        )));
                    }
                }
            }
            let vol6 = signed_volume6(&vertices, &u);
            let mut lmax: f64 = 0.0;
            for a in 0..4 {
                for b in (a + 1)..4 {
                    lmax = lmax.max(norm(sub(vertices[u[a]], vertices[u[b]])));
                }
            }
            if lmax <= DEGENERATE_RELATIVE_SIZE * diag
                || vol6.abs() <= DEGENERATE_RELATIVE_VOLUME * lmax * lmax * lmax
            {
                return Err(FeprError::Mesh(format!(
                    "tet {e} ({t:?}) is degenerate: volume {:.3e} m^3 for a longest edge of {:.3e} m \
                     (zero or near-zero volume; flat, collinear or coincident vertices)",
                    vol6 / 6.0,
                    lmax
                )));
            }
            if vol6 < 0.0 {
                u.swap(2, 3);
                report.flipped += 1;
            }
            for c in u {
                referenced[c] = true;
            }
            tets.push(u);
        }
        report.unreferenced = referenced.iter().filter(|r| !**r).count();
        Ok((Self { vertices, tets }, report))
    }

    /// A mesh from parts already known to be valid (a valid mesh's vertices and tets renamed by a permutation:
    /// [`crate::mesh::VertexOrder::mesh`]), without checking them again.
    pub(crate) fn from_valid_parts(vertices: Vec<Vec3>, tets: Vec<[usize; 4]>) -> Self {
        Self { vertices, tets }
    }

    /// Rest positions, metres.
    pub fn vertices(&self) -> &[Vec3] {
        &self.vertices
    }
    /// Tets, positively oriented.
    pub fn tets(&self) -> &[[usize; 4]] {
        &self.tets
    }
    pub fn num_vertices(&self) -> usize {
        self.vertices.len()
    }
    pub fn num_tets(&self) -> usize {
        self.tets.len()
    }

    /// Half the diagonal of the rest bounding box (the length scale `r` of fepr-spec section 2), metres.
    pub fn half_diagonal(&self) -> f64 {
        let mut lo = self.vertices[0];
        let mut hi = self.vertices[0];
        for v in &self.vertices {
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
        }
        0.5 * norm(sub(hi, lo))
    }

    /// Rest shape per tet: `D_m^-1` and volume.
    pub fn rest_shape(&self) -> RestShape {
        let mut dm_inv = Vec::with_capacity(self.tets.len());
        let mut volume = Vec::with_capacity(self.tets.len());
        for t in &self.tets {
            let dm = edge_matrix(&self.vertices, t);
            // Validation guarantees a non-degenerate tet, so the inverse exists.
            dm_inv.push(inverse(&dm).unwrap_or([[0.0; 3]; 3]));
            volume.push(det(&dm).abs() / 6.0);
        }
        RestShape { dm_inv, volume }
    }

    /// The boundary: every tet face no other tet shares, as a triangle wound outward (right-hand rule), in a
    /// fixed order (sorted by corner indices), so surface contact is deterministic.
    pub fn boundary_triangles(&self) -> Vec<[u32; 3]> {
        // Faces of a positively oriented tet (a, b, c, d), each wound so its normal points away from the
        // opposite corner.
        const FACES: [[usize; 3]; 4] = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]];
        let mut faces: Vec<([usize; 3], [u32; 3])> = Vec::with_capacity(4 * self.tets.len());
        for t in &self.tets {
            for f in FACES {
                let tri = f.map(|c| t[c] as u32);
                let mut key = f.map(|c| t[c]);
                key.sort_unstable();
                faces.push((key, tri));
            }
        }
        faces.sort_unstable_by_key(|f| f.0);
        let mut out = Vec::new();
        let mut k = 0;
        while k < faces.len() {
            let mut j = k + 1;
            while j < faces.len() && faces[j].0 == faces[k].0 {
                j += 1;
            }
            if j - k == 1 {
                out.push(faces[k].1);
            }
            k = j;
        }
        out
    }

    /// For each vertex, the list of `(tet * 4 + corner)` slots that touch it, in increasing order (CSR).
    /// The fixed order makes gathers deterministic for any thread count.
    pub fn vertex_incidence(&self) -> (Vec<usize>, Vec<u32>) {
        let m = self.vertices.len();
        let mut count = vec![0usize; m + 1];
        for t in &self.tets {
            for &v in t {
                count[v + 1] += 1;
            }
        }
        for i in 0..m {
            count[i + 1] += count[i];
        }
        let offsets = count.clone();
        let mut fill = count;
        let mut slots = vec![0u32; 4 * self.tets.len()];
        for (e, t) in self.tets.iter().enumerate() {
            for (c, &v) in t.iter().enumerate() {
                slots[fill[v]] = (4 * e + c) as u32;
                fill[v] += 1;
            }
        }
        (offsets, slots)
    }
}

/// Per-tet rest data: inverse rest edge matrix and rest volume (m^3).
#[derive(Clone, Debug)]
pub struct RestShape {
    pub dm_inv: Vec<Mat3>,
    pub volume: Vec<f64>,
}

/// How vertex masses are given.
#[derive(Clone, Debug, PartialEq)]
pub enum MassSpec {
    /// Density in kg/m^3, lumped: a quarter of each tet's mass to each of its vertices.
    Density(f64),
    /// The same mass for every vertex, kg.
    NodeMass(f64),
    /// One mass per vertex, kg.
    PerVertex(Vec<f64>),
}

/// Lumped vertex masses (kg). Every vertex must get a positive finite mass (an unreferenced vertex with a
/// density has none, which is an error naming the vertex).
pub fn lumped_masses(mesh: &TetMesh, rest: &RestShape, spec: &MassSpec) -> Result<Vec<f64>> {
    let m = mesh.num_vertices();
    let masses = match spec {
        MassSpec::Density(rho) => {
            if !(rho.is_finite() && *rho > 0.0) {
                return Err(invalid(
                    "density",
                    format!("must be a positive finite number of kg/m^3, got {rho}"),
                ));
            }
            let mut out = vec![0.0; m];
            for (t, vol) in mesh.tets().iter().zip(&rest.volume) {
                for &v in t {
                    out[v] += 0.25 * rho * vol;
                }
            }
            out
        }
        MassSpec::NodeMass(mass) => {
            if !(mass.is_finite() && *mass > 0.0) {
                return Err(invalid(
                    "node_mass",
                    format!("must be a positive finite number of kg, got {mass}"),
                ));
            }
            vec![*mass; m]
        }
        MassSpec::PerVertex(v) => {
            if v.len() != m {
                return Err(invalid(
                    "node_mass",
                    format!("has {} entries for {m} vertices", v.len()),
                ));
            }
            v.clone()
        }
    };
    for (i, &mi) in masses.iter().enumerate() {
        if !(mi.is_finite() && mi > 0.0) {
            let why = if matches!(spec, MassSpec::Density(_)) {
                "no tet references it, so a density gives it no mass (remove unreferenced vertices or give node masses)"
                    .to_string()
            } else {
                format!("its mass is {mi} kg; masses must be positive and finite")
            };
            return Err(invalid("mass", format!("vertex {i}: {why}")));
        }
    }
    Ok(masses)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A unit cube split into 6 tets around its main diagonal (0 -> 7), with vertex i at the binary
    /// coordinates of i. Used throughout the crate's tests.
    pub fn cube() -> (Vec<Vec3>, Vec<[i64; 4]>) {
        let v: Vec<Vec3> = (0..8)
            .map(|i| [(i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64])
            .collect();
        let t = vec![
            [0, 1, 3, 7],
            [0, 3, 2, 7],
            [0, 2, 6, 7],
            [0, 6, 4, 7],
            [0, 4, 5, 7],
            [0, 5, 1, 7],
        ];
        (v, t)
    }

    #[test]
    fn cube_builds_with_total_volume_one() {
        let (v, t) = cube();
        let (mesh, report) = TetMesh::new(v, &t).unwrap();
        let rest = mesh.rest_shape();
        let total: f64 = rest.volume.iter().sum();
        assert!((total - 1.0).abs() < 1e-14);
        assert_eq!(report.unreferenced, 0);
        for tet in mesh.tets() {
            assert!(signed_volume6(mesh.vertices(), tet) > 0.0);
        }
        let _ = report.flipped;
    }

    #[test]
    fn negatively_oriented_tets_are_repaired_and_counted() {
        let (v, mut t) = cube();
        t[0].swap(0, 1);
        t[3].swap(2, 3);
        let (mesh, report) = TetMesh::new(v, &t).unwrap();
        let flipped_before = report.flipped;
        assert!(flipped_before >= 2);
        for tet in mesh.tets() {
            assert!(signed_volume6(mesh.vertices(), tet) > 0.0);
        }
    }

    #[test]
    fn bad_meshes_get_errors_naming_the_tet() {
        let (v, t) = cube();
        let mut bad = t.clone();
        bad[2][1] = 8;
        let err = TetMesh::new(v.clone(), &bad).unwrap_err().to_string();
        assert!(
            err.contains("tet 2") && err.contains("out of range"),
            "{err}"
        );
        let mut bad = t.clone();
        bad[4][1] = -1;
        let err = TetMesh::new(v.clone(), &bad).unwrap_err().to_string();
        assert!(err.contains("tet 4") && err.contains("-1"), "{err}");
        let mut bad = t.clone();
        bad[1][3] = bad[1][0];
        let err = TetMesh::new(v.clone(), &bad).unwrap_err().to_string();
        assert!(err.contains("tet 1 repeats vertex"), "{err}");
        // A flat tet: four coplanar vertices.
        let err = TetMesh::new(v.clone(), &[[0, 1, 2, 3]])
            .unwrap_err()
            .to_string();
        assert!(err.contains("tet 0") && err.contains("degenerate"), "{err}");
        let mut vn = v.clone();
        vn[5][1] = f64::NAN;
        let err = TetMesh::new(vn, &t).unwrap_err().to_string();
        assert!(
            err.contains("vertex 5") && err.contains("non-finite"),
            "{err}"
        );
    }

    #[test]
    fn density_lumps_a_quarter_of_each_tet() {
        let (v, t) = cube();
        let (mesh, _) = TetMesh::new(v, &t).unwrap();
        let rest = mesh.rest_shape();
        let masses = lumped_masses(&mesh, &rest, &MassSpec::Density(1000.0)).unwrap();
        let total: f64 = masses.iter().sum();
        assert!((total - 1000.0).abs() < 1e-10);
        // Vertices 0 and 7 are in all six tets.
        assert!((masses[0] - 6.0 * 0.25 * 1000.0 / 6.0).abs() < 1e-10);
    }

    #[test]
    fn unreferenced_vertex_with_density_is_an_error_naming_it() {
        let (mut v, t) = cube();
        v.push([5.0, 5.0, 5.0]);
        let (mesh, report) = TetMesh::new(v, &t).unwrap();
        assert_eq!(report.unreferenced, 1);
        let rest = mesh.rest_shape();
        let err = lumped_masses(&mesh, &rest, &MassSpec::Density(1000.0))
            .unwrap_err()
            .to_string();
        assert!(err.contains("vertex 8"), "{err}");
    }
}

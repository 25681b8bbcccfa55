//! What a simulation carries from one step to the next, as named arrays of numbers: a checkpoint's core part.
//!
//! A run that stops and resumes from a [`Carry`] must take exactly the steps the uninterrupted run takes, bit
//! for bit. The settings (mesh, material, integrator, projection, obstacles, pins) are not in it: the caller
//! builds the simulation again from them and then resumes it ([`crate::simulation::Simulation::resume`]); the
//! carry holds what the steps themselves change (the state, the running references and books, the resting
//! rule's count, the projection's search and certificate memory, the kinematic pins' anchors). Every value is a
//! `f64` (counts and indices are exact below 2^53), so that a caller can store the carry in any array format.
//! Why not serde: the carry is a flat list of named arrays that NumPy writes and reads as they are, with a
//! version and a model key that the reader checks; a serialisation framework would add a dependency and a
//! format of its own for no gain.

use std::collections::BTreeMap;

use crate::error::{FeprError, Result};
use crate::math::Vec3;

/// The layout version of a [`Carry`]; a carry of another version is refused with a clear error.
pub const CARRY_VERSION: u32 = 2;

/// Named arrays of `f64`: what a step carries to the next (see the module docs).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Carry {
    entries: BTreeMap<String, Vec<f64>>,
}

impl Carry {
    pub fn new() -> Self {
        Self::default()
    }

    /// A carry from named arrays read back from storage.
    pub fn from_entries(entries: BTreeMap<String, Vec<f64>>) -> Self {
        Self { entries }
    }

    pub fn entries(&self) -> &BTreeMap<String, Vec<f64>> {
        &self.entries
    }

    pub fn put(&mut self, name: &str, values: Vec<f64>) {
        self.entries.insert(name.to_string(), values);
    }

    pub fn put_scalar(&mut self, name: &str, value: f64) {
        self.put(name, vec![value]);
    }

    pub fn put_option(&mut self, name: &str, value: Option<f64>) {
        self.put(name, value.into_iter().collect());
    }

    pub fn put_vec3s(&mut self, name: &str, rows: &[Vec3]) {
        self.put(name, rows.iter().flatten().copied().collect());
    }

    /// The array `name`, or an error saying that the checkpoint lacks it.
    pub fn get(&self, name: &str) -> Result<&[f64]> {
        self.entries
            .get(name)
            .map(Vec::as_slice)
            .ok_or_else(|| FeprError::Simulation(format!("the checkpoint has no '{name}' entry")))
    }

    /// The array `name`, which must hold `len` numbers.
    pub fn get_len(&self, name: &str, len: usize) -> Result<&[f64]> {
        let a = self.get(name)?;
        if a.len() != len {
            return Err(FeprError::Simulation(format!(
                "the checkpoint's '{name}' entry holds {} numbers where {len} are expected: it belongs to another \
                 mesh or settings",
                a.len()
            )));
        }
        Ok(a)
    }

    pub fn scalar(&self, name: &str) -> Result<f64> {
        Ok(self.get_len(name, 1)?[0])
    }

    /// A count or index stored as a number: it must be a non-negative integer.
    pub fn count(&self, name: &str) -> Result<usize> {
        let v = self.scalar(name)?;
        as_count(name, v)
    }

    pub fn option(&self, name: &str) -> Result<Option<f64>> {
        match self.get(name)? {
            [] => Ok(None),
            [v] => Ok(Some(*v)),
            a => Err(FeprError::Simulation(format!(
                "the checkpoint's '{name}' entry holds {} numbers where 0 or 1 are expected",
                a.len()
            ))),
        }
    }

    /// `rows` rows of 3 numbers.
    pub fn vec3s(&self, name: &str, rows: usize) -> Result<Vec<Vec3>> {
        Ok(self
            .get_len(name, 3 * rows)?
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect())
    }

    /// Rows of 3 numbers, as many as the entry holds.
    pub fn vec3s_any(&self, name: &str) -> Result<Vec<Vec3>> {
        let a = self.get(name)?;
        if a.len() % 3 != 0 {
            return Err(FeprError::Simulation(format!(
                "the checkpoint's '{name}' entry holds {} numbers, not rows of 3",
                a.len()
            )));
        }
        Ok(a.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    }
}

/// `v` as a count (a non-negative integer below 2^53), or an error naming the entry.
pub fn as_count(name: &str, v: f64) -> Result<usize> {
    if v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v < 9.007_199_254_740_992e15 {
        Ok(v as usize)
    } else {
        Err(FeprError::Simulation(format!(
            "the checkpoint's '{name}' entry holds {v}, not a count"
        )))
    }
}

/// A 64-bit key as two exact `f64` halves.
pub fn key_halves(bits: u64) -> Vec<f64> {
    vec![(bits >> 32) as f64, (bits & 0xffff_ffff) as f64]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_carry_gives_back_what_was_put_and_names_what_is_missing_or_malformed() {
        let mut c = Carry::new();
        c.put_vec3s("x", &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        c.put_option("none", None);
        c.put_option("some", Some(0.25));
        c.put_scalar("n", 7.0);
        c.put_scalar("bad", 1.5);
        assert_eq!(c.vec3s("x", 2).unwrap()[1], [4.0, 5.0, 6.0]);
        assert_eq!(c.option("none").unwrap(), None);
        assert_eq!(c.option("some").unwrap(), Some(0.25));
        assert_eq!(c.count("n").unwrap(), 7);
        assert!(c.count("bad").unwrap_err().to_string().contains("'bad'"));
        assert!(c
            .vec3s("x", 3)
            .unwrap_err()
            .to_string()
            .contains("another mesh"));
        assert!(c.get("y").unwrap_err().to_string().contains("no 'y' entry"));
        assert_eq!(key_halves(u64::MAX), vec![4294967295.0, 4294967295.0]);
    }
}

//! The per-particle fields `MpmSolver.get` and `set` copy, by name: their
//! table, their shapes and their reading and writing in the core's
//! `Particle`.

use hybridmpm_mpm as core;
use hybridmpm_mpm::{MpmError, Particle, Solver};
use nalgebra::SMatrix;
use pyo3::prelude::*;

use crate::errors::invalid_input;

/// The rank of a field's value per particle: 0 (a number), 1 (a vector of
/// `D`), 2 (a `D`×`D` matrix).
pub(crate) fn field_dim(field: &str) -> usize {
    match field {
        "positions" | "velocities" | "external_acceleration" => 1,
        "affine" | "deformation_gradient" | "stress" => 2,
        _ => 0,
    }
}

/// The fields, by name.
pub(crate) const FIELDS: &[&str] = &[
    "positions",
    "velocities",
    "affine",
    "deformation_gradient",
    "volume_ratio",
    "volume_correction",
    "masses",
    "volumes",
    "material",
    "material_set",
    "external_acceleration",
    "stress",
];

/// `InvalidInputError` (argument `field`) unless `field` is one of [`FIELDS`].
pub(crate) fn check_name(py: Python<'_>, field: &str) -> PyResult<()> {
    if FIELDS.contains(&field) {
        return Ok(());
    }
    Err(invalid_input(
        py,
        "field",
        format!("unknown field '{field}' (one of {})", FIELDS.join(", ")),
    ))
}

/// The shape of field `field` of `n` particles in `d` dimensions: `[n]`,
/// `[n, d]` or `[n, d, d]`.
pub(crate) fn shape(field: &str, n: usize, d: usize) -> Vec<usize> {
    match field_dim(field) {
        0 => vec![n],
        1 => vec![n, d],
        _ => vec![n, d, d],
    }
}

fn read_field<const D: usize>(p: &Particle<D>, field: &str, out: &mut Vec<f32>) {
    match field {
        "positions" => out.extend_from_slice(p.x.as_slice()),
        "velocities" => out.extend_from_slice(p.v.as_slice()),
        "external_acceleration" => out.extend_from_slice(p.ext.as_slice()),
        "affine" | "deformation_gradient" | "stress" => {
            let m = match field {
                "affine" => p.c,
                "deformation_gradient" => p.f,
                _ => p.stress(),
            };
            for r in 0..D {
                for c in 0..D {
                    out.push(m[(r, c)]);
                }
            }
        }
        "volume_ratio" => out.push(p.j),
        "volume_correction" => out.push(p.vc),
        "masses" => out.push(p.mass),
        "volumes" => out.push(p.volume),
        _ => {}
    }
}

fn write_field<const D: usize>(p: &mut Particle<D>, field: &str, v: &[f32]) {
    match field {
        "positions" => p.x.copy_from_slice(v),
        "velocities" => p.v.copy_from_slice(v),
        "external_acceleration" => p.ext.copy_from_slice(v),
        "affine" | "deformation_gradient" => {
            let m = SMatrix::<f32, D, D>::from_fn(|r, c| v[r * D + c]);
            if field == "affine" { p.c = m } else { p.f = m }
        }
        "volume_ratio" => p.j = v[0],
        "volume_correction" => p.vc = v[0],
        "masses" => p.mass = v[0],
        "volumes" => p.volume = v[0],
        _ => {}
    }
}

/// A copy of one per-particle field (public order): floats, or the material
/// codes and parameter-set indices.
pub(crate) enum Column {
    F32(Vec<f32>),
    I32(Vec<i32>),
}

pub(crate) fn read_column<const D: usize>(s: &Solver<D>, field: &str) -> (usize, Column)
where
    core::Dim<D>: core::DimOps<D>,
{
    let n = s.num_particles();
    if field == "material" || field == "material_set" {
        let mut m = Vec::with_capacity(n);
        if field == "material" {
            s.for_each_particle(|_, p| m.push(p.material as i32));
        } else {
            s.for_each_particle(|_, p| m.push(p.set as i32));
        }
        return (n, Column::I32(m));
    }
    let mut out = Vec::with_capacity(n * D.pow(field_dim(field) as u32));
    s.for_each_particle(|_, p| read_field(p, field, &mut out));
    (n, Column::F32(out))
}

pub(crate) fn write_column<const D: usize>(
    s: &mut Solver<D>,
    field: &str,
    flat: &[f32],
) -> core::Result<()>
where
    core::Dim<D>: core::DimOps<D>,
{
    let n = s.num_particles();
    let per = D.pow(field_dim(field) as u32);
    if flat.len() != n * per {
        return Err(MpmError::invalid(
            field,
            format!("the particle count changed to {n} while the call waited for another thread"),
        ));
    }
    let refresh = matches!(field, "affine" | "deformation_gradient" | "volume_ratio");
    s.modify_particles(refresh, |i, p| {
        write_field(p, field, &flat[i * per..(i + 1) * per])
    })
}

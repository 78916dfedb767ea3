//! Checkpoint / restore of the particle state and clock as bytes.
//!
//! Format (little endian): magic `HMPMCKP3`, `u32` D, `u64` N, `f64` time,
//! `u64` frame, then per particle `x, v, C, F` (f32), `j, vc, mass, volume`
//! (f32), `ext` (f32 × D), the derived stress τ (f32 × D², stored so that a
//! restored run continues bit-for-bit), `material` (u8), its parameter set
//! `set` (u16). Parameters are not included: the Python layer stores them
//! beside this blob. A `HMPMCKP2` blob (before parameter sets: no `set`)
//! restores with each particle in its material's default set.

use nalgebra::{SMatrix, SVector};

use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::particles::{Material, Particle};
use crate::solver::Solver;

const MAGIC: &[u8; 8] = b"HMPMCKP3";
const MAGIC_V2: &[u8; 8] = b"HMPMCKP2";
/// The format of a projection solver inside a step that spans frames: `MAGIC`'s, then the frames
/// left in the step (u32).
const MAGIC_V4: &[u8; 8] = b"HMPMCKP4";

fn put(out: &mut Vec<u8>, xs: &[f32]) {
    for x in xs {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8]> {
        if self.pos + n > self.buf.len() {
            return Err(MpmError::Checkpoint(format!(
                "truncated at byte {} (need {n} more)",
                self.pos
            )));
        }
        let s = &self.buf[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn f32(&mut self) -> Result<f32> {
        Ok(f32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    fn vec<const D: usize>(&mut self) -> Result<SVector<f32, D>> {
        let mut v = SVector::<f32, D>::zeros();
        for d in 0..D {
            v[d] = self.f32()?;
        }
        Ok(v)
    }
    fn mat<const D: usize>(&mut self) -> Result<SMatrix<f32, D, D>> {
        let mut m = SMatrix::<f32, D, D>::zeros();
        for i in 0..D * D {
            m[i] = self.f32()?;
        }
        Ok(m)
    }
}

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// Serialise the particle state and the clock.
    pub fn checkpoint(&self) -> Vec<u8> {
        let ps = self.particles();
        let mut out = Vec::with_capacity(40 + ps.len() * (4 * (3 * D + 3 * D * D + 4) + 3));
        out.extend_from_slice(if self.drift_frames() > 0 {
            MAGIC_V4
        } else {
            MAGIC
        });
        out.extend_from_slice(&(D as u32).to_le_bytes());
        out.extend_from_slice(&(ps.len() as u64).to_le_bytes());
        out.extend_from_slice(&self.time().to_le_bytes());
        out.extend_from_slice(&self.frame().to_le_bytes());
        for p in ps {
            put(&mut out, p.x.as_slice());
            put(&mut out, p.v.as_slice());
            put(&mut out, p.c.as_slice());
            put(&mut out, p.f.as_slice());
            put(&mut out, &[p.j, p.vc, p.mass, p.volume]);
            put(&mut out, p.ext.as_slice());
            put(&mut out, p.stress().as_slice());
            out.push(p.material as u8);
            out.extend_from_slice(&p.set.to_le_bytes());
        }
        if self.drift_frames() > 0 {
            out.extend_from_slice(&self.drift_frames().to_le_bytes());
        }
        out
    }

    /// Restore a state written by [`Solver::checkpoint`]. On error the solver is unchanged.
    pub fn restore(&mut self, blob: &[u8]) -> Result<()> {
        let mut r = Reader { buf: blob, pos: 0 };
        let magic = r.take(8)?;
        let drift = magic == MAGIC_V4;
        let with_set = magic == MAGIC || drift;
        if !with_set && magic != MAGIC_V2 {
            return Err(MpmError::Checkpoint(
                "not a hybridmpm MPM checkpoint (bad magic)".into(),
            ));
        }
        let d = u32::from_le_bytes(r.take(4)?.try_into().unwrap()) as usize;
        if d != D {
            return Err(MpmError::Checkpoint(format!(
                "checkpoint is {d}D, solver is {D}D"
            )));
        }
        let n = r.u64()? as usize;
        let per = 4 * (3 * D + 3 * D * D + 4) + if with_set { 3 } else { 1 };
        if n.checked_mul(per).is_none_or(|b| b > blob.len()) {
            return Err(MpmError::Checkpoint(format!(
                "declares {n} particles but holds {} bytes",
                blob.len()
            )));
        }
        let time = f64::from_le_bytes(r.take(8)?.try_into().unwrap());
        let frame = r.u64()?;
        let mut ps = Vec::with_capacity(n);
        for _ in 0..n {
            let x = r.vec::<D>()?;
            let v = r.vec::<D>()?;
            let c = r.mat::<D>()?;
            let f = r.mat::<D>()?;
            let (j, vc, mass, volume) = (r.f32()?, r.f32()?, r.f32()?, r.f32()?);
            let ext = r.vec::<D>()?;
            let tau = r.mat::<D>()?;
            let code = r.take(1)?[0];
            let material = Material::from_code(code as i64)
                .ok_or_else(|| MpmError::Checkpoint(format!("unknown material code {code}")))?;
            let mut p = Particle::new(x, material, mass, volume);
            if with_set {
                p.set = u16::from_le_bytes(r.take(2)?.try_into().unwrap());
            }
            p.v = v;
            p.c = c;
            p.f = f;
            p.j = j;
            p.vc = vc;
            p.ext = ext;
            p.tau = tau;
            ps.push(p);
        }
        let drift_frames = if drift {
            u32::from_le_bytes(r.take(4)?.try_into().unwrap())
        } else {
            0
        };
        if r.pos != blob.len() {
            return Err(MpmError::Checkpoint(format!(
                "{} trailing bytes",
                blob.len() - r.pos
            )));
        }
        if !time.is_finite() {
            return Err(MpmError::Checkpoint("non-finite time".into()));
        }
        let before = self.drift_frames();
        self.set_drift_frames(drift_frames)?;
        self.set_drift_frames(before)?; // checked first: on error the solver is unchanged
        self.set_particles_keep_stress(ps)
            .map_err(|e| MpmError::Checkpoint(e.to_string()))?;
        self.set_clock(time, frame);
        self.set_drift_frames(drift_frames)?;
        Ok(())
    }
}

//! Tests of the frame loop (`frame.rs`): the team, the compiled copies, the
//! block sort's two ways and g2p's items give the bits of one thread.
use super::super::Solver;
use super::super::grid::G2P_WINDOW;
use crate::dim::{Dim, DimOps};
use crate::isa::Isa;
use crate::params::SolverParams;
use crate::particles::{Material, Particle, lattice};

/// A water and a sand block falling and colliding, stepped `frames`
/// frames with `threads` threads, the team forced on or off.
fn run<const D: usize>(threads: usize, team: bool, frames: usize) -> Vec<u8>
where
    Dim<D>: DimOps<D>,
{
    run_with::<D>(Isa::Baseline, threads, team, frames)
}

/// [`run`] with the block sort in chunks (`serial` false) or whole in
/// a serial section (true) whatever the particle count.
fn run_sorted<const D: usize>(threads: usize, team: bool, frames: usize, serial: bool) -> Vec<u8>
where
    Dim<D>: DimOps<D>,
{
    run_full::<D>(Isa::Baseline, threads, team, frames, Some(serial))
}

/// [`run`] with the frame loop's copy for `isa`.
fn run_with<const D: usize>(isa: Isa, threads: usize, team: bool, frames: usize) -> Vec<u8>
where
    Dim<D>: DimOps<D>,
{
    run_full::<D>(isa, threads, team, frames, None)
}

fn run_full<const D: usize>(
    isa: Isa,
    threads: usize,
    team: bool,
    frames: usize,
    serial_sort: Option<bool>,
) -> Vec<u8>
where
    Dim<D>: DimOps<D>,
{
    let params = SolverParams::<D> {
        n_grid: 48,
        num_threads: threads,
        ..Default::default()
    };
    let dx = params.dx();
    let mut s = Solver::new(params, vec![]).unwrap();
    let mut ps = lattice([0.1; D], 20, dx / 2.0, Material::Water, 1000.0);
    ps.extend(lattice([0.45; D], 14, dx / 2.0, Material::Sand, 1000.0));
    s.set_particles(ps).unwrap();
    s.mode.force = Some(team);
    if let Some(serial) = serial_sort {
        s.serial_sort_below = if serial { usize::MAX } else { 0 };
    }
    s.set_isa(isa).unwrap();
    for _ in 0..frames {
        s.step_frame(2.5e-3).unwrap();
    }
    s.checkpoint()
}

/// The team's chunked block sort and claimed blocks give bitwise the
/// result of one thread, for teams of 2 and 3 (more threads than this
/// machine's cores: members are descheduled mid-stage), 2D and 3D.
#[test]
fn team_is_bitwise_identical_to_one_thread() {
    let one = run::<2>(1, false, 12);
    assert_eq!(one, run::<2>(2, true, 12));
    assert_eq!(one, run::<2>(3, true, 12));
    assert_eq!(one, run::<2>(2, false, 12));
    let one = run::<3>(1, false, 6);
    assert_eq!(one, run::<3>(2, true, 6));
    assert_eq!(one, run::<3>(3, true, 6));
}

/// Water and two sand sets interleaved particle by particle in 3D, thrown
/// into a corner (sand yields, and some of its batches take the eigenvalue
/// route): teams of 2 and 3, which cut blocks into other pieces, give the
/// bits of one thread (g2p's batches end at its windows, `G2P_WINDOW`).
#[test]
fn interleaved_materials_keep_one_threads_bits_on_a_team_in_3d() {
    use crate::material::{MaterialParams, SandParams};
    use nalgebra::SVector;
    let run = |threads: usize, team: bool| {
        let params = SolverParams::<3> {
            n_grid: 32,
            num_threads: threads,
            sets: vec![MaterialParams::Sand(SandParams {
                friction_angle_deg: 40.0,
                youngs_modulus: 2.0e4,
                ..Default::default()
            })],
            ..Default::default()
        };
        let dx = params.dx();
        let mut ps = lattice([0.3; 3], 14, dx / 2.0, Material::Sand, 1500.0);
        for (i, p) in ps.iter_mut().enumerate() {
            match i % 3 {
                0 => *p = Particle::new(p.x, Material::Water, 1000.0 * p.volume, p.volume),
                2 => p.set = 5,
                _ => {}
            }
            p.v = SVector::from([3.0, -6.0, 2.0]);
        }
        let mut s = Solver::new(params, vec![]).unwrap();
        s.set_particles(ps).unwrap();
        s.mode.force = Some(team);
        for _ in 0..20 {
            s.step_frame(2.5e-3).unwrap();
        }
        s.checkpoint()
    };
    let one = run(1, false);
    // (not assert_eq: a difference would print both checkpoints)
    assert!(one == run(2, true), "a team of 2 changed the bits");
    assert!(one == run(3, true), "a team of 3 changed the bits");
}

/// Solvers asking for one thread count share the process's pool
/// ([`crate::pool::shared_pool`]), other counts get other pools, a pool no
/// solver holds any more is gone; and four teams stepping at once on one
/// shared pool of two threads (more team members than the pool has
/// threads: a member waits for a pool thread busy with another frame's
/// member) each give the bits of one thread and finish.
#[test]
fn solvers_share_a_pool_and_concurrent_teams_keep_their_bits() {
    use std::sync::Arc;
    // a thread count no other test asks for: the other tests run at the
    // same time, and a pool they hold would outlive this test's solvers
    let make = |threads: usize| {
        let params = SolverParams::<2> {
            n_grid: 16,
            num_threads: threads,
            ..Default::default()
        };
        Solver::new(params, vec![]).unwrap()
    };
    let (a, b, c) = (make(5), make(5), make(6));
    assert!(Arc::ptr_eq(&a.pool, &b.pool));
    assert!(!Arc::ptr_eq(&a.pool, &c.pool));
    assert_eq!(a.pool.current_num_threads(), 5);
    let gone = Arc::downgrade(&a.pool);
    drop((a, b));
    assert!(gone.upgrade().is_none(), "the pool outlived its solvers");

    let one = run::<2>(1, false, 12);
    let teams: Vec<_> = (0..4)
        .map(|_| std::thread::spawn(|| run::<2>(2, true, 12)))
        .collect();
    for t in teams {
        assert_eq!(t.join().unwrap(), one);
    }
}

/// The block sort gives the same bits whole in a serial section and in
/// chunks between barriers, alone and on teams of 2 and 3 (g2p's pieces
/// of blocks: `Solver::schedule`).
#[test]
fn the_serial_and_the_chunked_sort_give_the_same_bits() {
    let one = run_sorted::<2>(1, false, 12, false);
    for (threads, serial) in [(1, true), (2, true), (2, false), (3, true), (3, false)] {
        assert_eq!(
            one,
            run_sorted::<2>(threads, true, 12, serial),
            "2D {threads} {serial}"
        );
    }
    let one = run_sorted::<3>(1, false, 6, false);
    for (threads, serial) in [(2, true), (2, false), (3, false)] {
        assert_eq!(
            one,
            run_sorted::<3>(threads, true, 6, serial),
            "3D {threads} {serial}"
        );
    }
}

/// g2p's items cover every place of the sorted order once, each inside
/// its block; on a team, large blocks are cut, each member owns a run of
/// blocks in key order (about its share of the particles), the g2p items
/// of those blocks and the output blocks they first reach, its items come
/// largest first, and p2g's order is a permutation of the blocks.
#[test]
fn g2p_items_cover_every_particle_once() {
    let params = SolverParams::<2> {
        n_grid: 48,
        num_threads: 2,
        ..Default::default()
    };
    let dx = params.dx();
    let mut s = Solver::new(params, vec![]).unwrap();
    s.set_particles(lattice([0.1; 2], 40, dx / 2.0, Material::Water, 1000.0))
        .unwrap();
    s.step_frame(2.5e-3).unwrap();
    for members in [1, 2, 3] {
        s.schedule(members);
        let g = &s.grid;
        let n_src = g.src_blocks.len();
        let mut seen = vec![0u8; s.particles.len()];
        for it in &g.g2p_items {
            let b = it.block as usize;
            assert!(g.src_offsets[b] <= it.first && it.first + it.len <= g.src_offsets[b + 1]);
            // a piece starts at one of g2p's windows
            assert!((it.first - g.src_offsets[b]).is_multiple_of(G2P_WINDOW as u32));
            for k in it.first..it.first + it.len {
                seen[k as usize] += 1;
            }
        }
        assert!(seen.iter().all(|&c| c == 1), "{members}");
        let mut order = g.p2g_order.clone();
        order.sort_unstable();
        assert!(
            order.iter().enumerate().all(|(i, &b)| i as u32 == b),
            "{members}"
        );
        let ranges = [&g.p2g_bounds, &g.g2p_bounds, &g.grid_bounds];
        let ends = [n_src, g.g2p_items.len(), g.out_blocks.len()];
        for (bounds, end) in ranges.iter().zip(ends) {
            assert_eq!(bounds.len(), members + 1, "{members}");
            assert_eq!((bounds[0], bounds[members]), (0, end as u32));
            assert!(bounds.windows(2).all(|w| w[0] <= w[1]));
        }
        for m in 0..members {
            let blocks = &g.p2g_order[g.p2g_bounds[m] as usize..g.p2g_bounds[m + 1] as usize];
            let items = &g.g2p_items[g.g2p_bounds[m] as usize..g.g2p_bounds[m + 1] as usize];
            // the member's blocks are a run in key order, and its items theirs
            let lo = g.p2g_bounds[m];
            let mut own = blocks.to_vec();
            own.sort_unstable();
            assert!(own.iter().enumerate().all(|(i, &b)| b == lo + i as u32));
            assert!(items.iter().all(|it| own.binary_search(&it.block).is_ok()));
            if members > 1 {
                assert!(items.windows(2).all(|w| w[0].len >= w[1].len));
                let len = |b: u32| g.src_offsets[b as usize + 1] - g.src_offsets[b as usize];
                assert!(blocks.windows(2).all(|w| len(w[0]) >= len(w[1])));
                // a member's share is within a block of n / members
                let share = items.iter().map(|it| it.len).sum::<u32>() as f64;
                let largest = (0..n_src as u32).map(len).max().unwrap() as f64;
                let fair = s.particles.len() as f64 / members as f64;
                assert!(
                    (share - fair).abs() <= largest,
                    "{members} {m} {share} {fair}"
                );
            }
        }
        if members > 1 {
            assert!(g.g2p_items.len() > n_src, "{members}");
        } else {
            assert_eq!(g.g2p_items.len(), n_src);
        }
    }
}

/// Every compiled copy of the frame loop this CPU runs (`crate::isa`)
/// gives the bits of the portable one, alone and on a team, 2D and 3D,
/// water and sand (the blocks collide, so sand yields). On a CPU without
/// x86-64-v3 only the portable copy is compared with itself; the
/// machines this project is tested on have it.
#[test]
fn every_isa_gives_the_bits_of_the_portable_copy() {
    let base2 = run::<2>(1, false, 12);
    let base3 = run::<3>(1, false, 6);
    for isa in Isa::ALL.into_iter().filter(|i| i.available()) {
        assert_eq!(base2, run_with::<2>(isa, 1, false, 12), "{isa:?} 2D");
        assert_eq!(base2, run_with::<2>(isa, 2, true, 12), "{isa:?} 2D team");
        assert_eq!(base3, run_with::<3>(isa, 1, false, 6), "{isa:?} 3D");
        assert_eq!(base3, run_with::<3>(isa, 2, true, 6), "{isa:?} 3D team");
    }
    let mut s = Solver::<2>::new(SolverParams::default(), vec![]).unwrap();
    assert!(s.isa().available());
    for isa in Isa::ALL {
        assert_eq!(s.set_isa(isa).is_ok(), isa.available(), "{isa:?}");
    }
}

/// `mode_runs` counts each frame attempt under the way it ran: the team
/// (forced on, 2 threads), the thread alone (forced off, or a pool of one
/// thread, where "the team" is the calling thread).
#[test]
fn mode_runs_count_the_way_each_frame_ran() {
    for (threads, team, alone_expected) in [(2, true, false), (2, false, true), (1, true, true)] {
        let params = SolverParams::<2> {
            n_grid: 32,
            num_threads: threads,
            ..Default::default()
        };
        let dx = params.dx();
        let mut s = Solver::new(params, vec![]).unwrap();
        s.set_particles(lattice([0.2; 2], 10, dx / 2.0, Material::Water, 1000.0))
            .unwrap();
        s.mode.force = Some(team);
        assert_eq!(s.mode_runs(), (0, 0));
        for _ in 0..5 {
            s.step_frame(2.5e-3).unwrap();
        }
        let (alone, on_team) = s.mode_runs();
        assert!(
            alone + on_team >= 5,
            "{threads} {team}: {alone} + {on_team}"
        );
        assert_eq!(
            (alone > 0, on_team > 0),
            (alone_expected, !alone_expected),
            "{threads} {team}"
        );
    }
}

/// A frame attempt that fails after some substeps (which update the
/// particles where they are stored, on a shuffled storage order) and may
/// not retry leaves the state of its start, bit for bit, and the solver
/// steps on from it as a fresh one restored there does: on one thread, and
/// on a team both ways it keeps that start: a small frame's team (one sort
/// chunk) reorders the particles every substep and copies the start
/// (`start_copied`); a larger frame's team, like one thread, reorders in the
/// first substep only and keeps the start in the other buffer.
#[test]
fn a_frame_failing_in_a_later_substep_rolls_back_to_its_start() {
    use nalgebra::SVector;
    // (threads, the team, one sort chunk)
    for (threads, team, one_chunk) in [(1, false, false), (2, true, true), (2, true, false)] {
        let case = format!("{threads} threads, one chunk: {one_chunk}");
        let params = SolverParams::<2> {
            substeps: Some(8),
            max_substeps: 8,
            num_threads: threads,
            ..Default::default()
        };
        let mut s = Solver::new(params.clone(), vec![]).unwrap();
        let mut ps = lattice([0.3; 2], 24, params.dx() / 2.0, Material::Water, 1000.0);
        for p in &mut ps {
            p.v = SVector::<f32, 2>::new(3.0, 0.0);
        }
        s.set_particles(ps).unwrap();
        s.mode.force = Some(team);
        s.serial_sort_below = if one_chunk { usize::MAX } else { 0 };
        for _ in 0..6 {
            s.step_frame(2.5e-3).unwrap();
        }
        assert_eq!(s.start_copied, one_chunk, "{case}");
        let before = s.checkpoint();
        // +6 m/s a substep along x: the CFL bound (dx per substep, 25 m/s)
        // breaks after a few substeps, not the first
        let dt = 2.5e-3 / 8.0;
        s.modify_particles(false, |_, p| p.ext = SVector::<f32, 2>::new(6.0 / dt, 0.0))
            .unwrap();
        let with_ext = s.checkpoint();
        let err = s.step_frame(2.5e-3).unwrap_err();
        assert!(
            matches!(err, crate::MpmError::CflViolation { substep, .. } if substep >= 1),
            "{case}: {err:?}"
        );
        assert_eq!(s.mode_runs().1, if team { 7 } else { 0 }, "{case}");
        assert_eq!(with_ext, s.checkpoint(), "{case}");
        s.modify_particles(false, |_, p| p.ext = SVector::<f32, 2>::zeros())
            .unwrap();
        assert_eq!(before, s.checkpoint(), "{case}");
        let mut fresh = Solver::new(params, vec![]).unwrap();
        fresh.restore(&before).unwrap();
        fresh.mode.force = Some(team);
        fresh.serial_sort_below = s.serial_sort_below;
        for _ in 0..3 {
            s.step_frame(2.5e-3).unwrap();
            fresh.step_frame(2.5e-3).unwrap();
        }
        assert_eq!(s.checkpoint(), fresh.checkpoint(), "{case}");
    }
}

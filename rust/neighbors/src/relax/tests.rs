//! Tests of the relaxation; the plain implementation it must match bit for
//! bit is `reference.rs`.

use super::reference::relax_reference;
use super::*;

#[test]
fn the_separation_cache_changes_no_bit() {
    // a lattice compressed throughout: nearly every pair changes in every
    // iteration (the cache's pass over all pairs)
    let lattice: Vec<[f32; 2]> = (0..900)
        .map(|i| [(i % 30) as f32 * 0.011, (i / 30) as f32 * 0.013])
        .collect();
    let movable = vec![true; lattice.len()];
    for iterations in [2usize, 5] {
        let params = RelaxParams {
            radius: 0.04,
            rest_density: 4.0,
            iterations,
            omega: 1.0,
        };
        let (mut a, mut b) = (lattice.clone(), lattice.clone());
        assert_eq!(
            relax_density(&mut a, &movable, &params).unwrap(),
            relax_reference(&mut b, &movable, &params).unwrap()
        );
        assert!(a.iter().zip(&lattice).filter(|(p, q)| p != q).count() > 800);
        assert!(
            a.iter()
                .zip(&b)
                .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)),
            "compressed lattice, {iterations} iterations"
        );
    }
    // clouds with compressed clumps, stacks on one point and obstacles, 2D and 3D
    for seed in 0..6u32 {
        let mut x2: Vec<[f32; 2]> = (0..400)
            .map(|i| {
                let t = (i as u32 * 7919 + seed * 104_729) as f32;
                [(t * 0.618_034).fract(), (t * 0.754_877_7).fract()]
            })
            .collect();
        for p in x2.iter_mut().take(30) {
            *p = [0.5 + 0.001 * p[0], 0.5 + 0.001 * p[1]]; // a clump
        }
        for p in x2.iter_mut().skip(30).take(8) {
            *p = [0.0, 0.0]; // a stack on one point
        }
        let movable: Vec<bool> = (0..x2.len()).map(|i| i % 11 != 3).collect();
        let rho0 = 2.0 + seed as f32 * 0.5;
        for iterations in [1usize, 3, 7] {
            let params = RelaxParams {
                radius: 0.08,
                rest_density: rho0,
                iterations,
                omega: 1.0,
            };
            let (mut a, mut b) = (x2.clone(), x2.clone());
            let sa = relax_density(&mut a, &movable, &params).unwrap();
            let sb = relax_reference(&mut b, &movable, &params).unwrap();
            assert_eq!(sa, sb);
            assert!(
                a.iter()
                    .zip(&b)
                    .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)),
                "2D seed {seed}, {iterations} iterations"
            );
        }
        let x3: Vec<[f32; 3]> = x2
            .iter()
            .enumerate()
            .map(|(i, p)| [p[0], p[1], ((i as f32) * 0.381_966).fract() * 0.3])
            .collect();
        let params = RelaxParams {
            radius: 0.12,
            rest_density: rho0,
            iterations: 3,
            omega: 1.0,
        };
        let (mut a, mut b) = (x3.clone(), x3.clone());
        assert_eq!(
            relax_density(&mut a, &movable, &params).unwrap(),
            relax_reference(&mut b, &movable, &params).unwrap()
        );
        assert!(
            a.iter()
                .zip(&b)
                .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)),
            "3D seed {seed}"
        );
    }
}

#[test]
fn the_parallel_path_matches_the_reference_bit_for_bit() {
    // above SERIAL_PARTICLES the iterations run on rayon; below it on the calling thread
    // (the test above): both must give the reference's bits, on two threads as on one
    let n = crate::SERIAL_PARTICLES + 3000;
    assert!(crate::uses_rayon(n) && !crate::uses_rayon(400));
    let mut x: Vec<[f32; 2]> = (0..n)
        .map(|i| {
            let t = i as f32;
            [(t * 0.618_034).fract(), (t * 0.754_877_7).fract()]
        })
        .collect();
    for p in x.iter_mut().take(300) {
        *p = [0.25 + 0.002 * p[0], 0.75 + 0.002 * p[1]]; // a clump
    }
    let movable: Vec<bool> = (0..n).map(|i| i % 13 != 5).collect();
    let params = RelaxParams {
        radius: 0.02,
        rest_density: 4.0,
        iterations: 3,
        omega: 1.0,
    };
    let mut want = x.clone();
    let sw = relax_reference(&mut want, &movable, &params).unwrap();
    assert!(sw.compressed_before > 200, "{sw:?}");
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let mut got = x.clone();
        let sg = pool.install(|| relax_density(&mut got, &movable, &params).unwrap());
        assert_eq!(sg, sw);
        assert!(
            got.iter()
                .zip(&want)
                .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits)),
            "{threads} threads"
        );
    }
}

/// `relax_density`, the clip and `radius_graph` one after the other.
fn in_turn<const D: usize>(
    x: &[[f32; D]],
    movable: &[bool],
    params: &RelaxParams,
    bounds: Option<([f32; D], [f32; D])>,
    graph: &GraphParams,
) -> (Vec<[f32; D]>, RelaxStats, usize, crate::Graph<D>) {
    let mut p = x.to_vec();
    if let Some((lo, hi)) = bounds {
        for q in p.iter_mut() {
            for k in 0..D {
                q[k] = q[k].clamp(lo[k], hi[k]);
            }
        }
    }
    let stats = relax_density(&mut p, movable, params).unwrap();
    let mut clamped = 0;
    if let Some((lo, hi)) = bounds {
        for q in p.iter_mut() {
            let before = *q;
            for k in 0..D {
                q[k] = if q[k] < lo[k] {
                    lo[k]
                } else if q[k] > hi[k] {
                    hi[k]
                } else {
                    q[k]
                };
            }
            clamped += (before != *q) as usize;
        }
    }
    let g = radius_graph(&p, graph).unwrap();
    (p, stats, clamped, g)
}

fn fused<const D: usize>(
    x: &[[f32; D]],
    movable: &[bool],
    params: &RelaxParams,
    bounds: Option<([f32; D], [f32; D])>,
    graph: &GraphParams,
) -> (Vec<[f32; D]>, RelaxedGraph, crate::Graph<D>) {
    let mut p = x.to_vec();
    let r = relax_then_graph(&mut p, movable, params, bounds, graph).unwrap();
    let e = r.senders.len();
    let mut g = crate::Graph::<D> {
        senders: vec![0; e],
        receivers: vec![0; e],
        displacement: vec![[0.0; D]; e],
        distance: vec![0.0; e],
        dropped: r.dropped,
    };
    crate::write_edges(
        &p,
        &r.offsets,
        &r.senders,
        &mut g.senders,
        &mut g.receivers,
        &mut g.displacement,
        &mut g.distance,
    )
    .unwrap();
    (p, r, g)
}

fn same_bits<const D: usize>(a: &[[f32; D]], b: &[[f32; D]]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(p, q)| p.map(f32::to_bits) == q.map(f32::to_bits))
}

#[test]
fn relax_then_graph_is_relax_clip_and_graph_in_turn() {
    // clouds with a few compressed clumps (few particles move: the lists
    // are updated) and compressed throughout (most move: searched from
    // scratch), some particles pushed past the bounds, 2D and 3D, with
    // and without self-edges, a cap and another radius
    let mut updated = 0;
    let mut scratch = 0;
    for seed in 0..8u32 {
        // a jittered lattice (spacing 0.04, about 7 neighbours within R = 0.06)
        let mut state = 0x9e37_79b9_7f4a_7c15u64 ^ seed as u64;
        let mut rnd = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut x2: Vec<[f32; 2]> = (0..600)
            .map(|i| {
                let (a, b) = ((i % 25) as f32, (i / 25) as f32);
                [
                    0.02 + 0.04 * a + 0.01 * rnd(),
                    0.02 + 0.04 * b + 0.01 * rnd(),
                ]
            })
            .collect();
        // the rest density of the cloud before the clumps (nothing else compressed)
        let rho_max = kernel_density(&x2, 0.06)
            .unwrap()
            .into_iter()
            .fold(0.0f32, f32::max);
        for k in 0..(4 + 3 * seed as usize) {
            // clumps by the lower wall
            let c = [0.2 + 0.1 * (k % 5) as f32, 0.03];
            x2[k * 7] = [c[0] + 0.01 * rnd(), c[1] + 0.01 * rnd()];
        }
        let movable: Vec<bool> = (0..x2.len()).map(|i| i % 13 != 5).collect();
        let bounds = Some(([0.025f32, 0.03], [0.99f32, 0.99]));
        let rho0 = if seed % 4 == 3 { 0.5 } else { rho_max * 1.01 };
        for (iterations, self_edges, cap, radius) in [
            (3usize, true, None, 0.06f32),
            (1, false, None, 0.06),
            (3, true, Some(6), 0.06),
            (3, true, None, 0.05),
        ] {
            let params = RelaxParams {
                radius: 0.06,
                rest_density: rho0,
                iterations,
                omega: 1.0,
            };
            let graph = GraphParams {
                radius,
                self_edges,
                max_neighbors: cap,
                max_edges: None,
            };
            let (pa, sa, ca, ga) = in_turn(&x2, &movable, &params, bounds, &graph);
            let (pb, rb, gb) = fused(&x2, &movable, &params, bounds, &graph);
            assert!(same_bits(&pa, &pb), "2D seed {seed}");
            assert_eq!((sa, ca), (rb.stats, rb.clamped));
            assert_eq!(
                ga, gb,
                "2D seed {seed} {iterations} {self_edges} {cap:?} {radius}"
            );
            if rb.searched < x2.len() {
                updated += 1;
            } else {
                scratch += 1;
            }
        }
        let x3: Vec<[f32; 3]> = x2
            .iter()
            .enumerate()
            .map(|(i, p)| [p[0], p[1], ((i as f32) * 0.381_966).fract() * 0.2])
            .collect();
        let params = RelaxParams {
            radius: 0.09,
            rest_density: rho0,
            iterations: 3,
            omega: 1.0,
        };
        let graph = GraphParams {
            radius: 0.09,
            ..GraphParams::default()
        };
        let b3 = Some(([0.0f32, 0.015, 0.0], [1.0f32, 1.0, 0.15]));
        let (pa, sa, ca, ga) = in_turn(&x3, &movable, &params, b3, &graph);
        let (pb, rb, gb) = fused(&x3, &movable, &params, b3, &graph);
        assert!(same_bits(&pa, &pb), "3D seed {seed}");
        assert_eq!((sa, ca), (rb.stats, rb.clamped));
        assert_eq!(ga, gb, "3D seed {seed}");
        assert!(rb.clamped > 0, "the 3D bounds cut the cloud");
    }
    assert!(
        updated >= 4 && scratch >= 8,
        "both ways taken: {updated} updated, {scratch} from scratch"
    );
    // nothing to relax: the relaxation's lists, with the self-edges
    let x: Vec<[f32; 2]> = (0..50)
        .map(|i| [(i % 10) as f32 * 0.1, (i / 10) as f32 * 0.1])
        .collect();
    let params = RelaxParams {
        radius: 0.15,
        rest_density: 100.0,
        iterations: 3,
        omega: 1.0,
    };
    let graph = GraphParams {
        radius: 0.15,
        ..GraphParams::default()
    };
    let (_, rb, gb) = fused(&x, &[true; 50], &params, None, &graph);
    assert_eq!(rb.searched, 0);
    assert_eq!(gb, radius_graph(&x, &graph).unwrap());
    // empty input, bad bounds
    let (p, rb, gb) = fused::<3>(&[], &[], &params, None, &graph);
    assert!(p.is_empty() && rb.senders.is_empty() && gb.is_empty());
    let mut y = x.clone();
    let bad = relax_then_graph(
        &mut y,
        &[true; 50],
        &params,
        Some(([0.5, 0.0], [0.4, 1.0])),
        &graph,
    );
    assert!(matches!(
        bad,
        Err(GraphError::InvalidInput {
            field: "bounds",
            ..
        })
    ));
    assert!(same_bits(&x, &y));
}

fn lattice(n: usize, h: f32) -> Vec<[f32; 2]> {
    let mut v = Vec::new();
    for i in 0..n {
        for j in 0..n {
            v.push([i as f32 * h, j as f32 * h]);
        }
    }
    v
}

fn brute_density(x: &[[f32; 2]], r: f32) -> Vec<f32> {
    x.iter()
        .map(|a| {
            x.iter()
                .map(|b| {
                    let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
                    kernel(d / r)
                })
                .sum()
        })
        .collect()
}

#[test]
fn kernel_density_matches_brute_force() {
    let x: Vec<[f32; 2]> = (0..200)
        .map(|i| {
            let t = i as f32;
            [(t * 0.618_034).fract(), (t * 0.754_877_7).fract()]
        })
        .collect();
    let rho = kernel_density(&x, 0.1).unwrap();
    for (a, b) in rho.iter().zip(brute_density(&x, 0.1)) {
        assert!((a - b).abs() < 1e-5, "{a} vs {b}");
    }
}

#[test]
fn a_compressed_lattice_expands_and_one_at_rest_does_not_move() {
    let r = 2.0;
    let rest = lattice(8, 1.0);
    let rho0 = kernel_density(&rest, r)
        .unwrap()
        .into_iter()
        .fold(0.0f32, f32::max);
    let params = RelaxParams {
        radius: r,
        rest_density: rho0,
        iterations: 5,
        omega: 1.0,
    };
    let movable = vec![true; rest.len()];
    let mut same = rest.clone();
    let st = relax_density(&mut same, &movable, &params).unwrap();
    assert_eq!(
        same, rest,
        "no particle is denser than rho_0: nothing moves"
    );
    assert_eq!(st.compressed_before, 0);
    // squeezed to 80% spacing: denser; the relaxation lowers the peak density
    let mut squeezed = lattice(8, 0.8);
    let before = kernel_density(&squeezed, r).unwrap();
    let st = relax_density(&mut squeezed, &movable, &params).unwrap();
    let after = kernel_density(&squeezed, r).unwrap();
    let peak = |v: &[f32]| v.iter().copied().fold(0.0f32, f32::max);
    assert!(st.compressed_before > 0 && st.max_compression_before > 0.1);
    assert!(
        peak(&after) - rho0 < 0.5 * (peak(&before) - rho0),
        "{} -> {}",
        peak(&before),
        peak(&after)
    );
    // momentum-like symmetry: the centroid stays (pairwise equal and opposite moves)
    let c = |v: &[[f32; 2]]| {
        let s = v
            .iter()
            .fold([0.0f64; 2], |a, p| [a[0] + p[0] as f64, a[1] + p[1] as f64]);
        [s[0] / v.len() as f64, s[1] / v.len() as f64]
    };
    let (c0, c1) = (c(&lattice(8, 0.8)), c(&squeezed));
    assert!((c0[0] - c1[0]).abs() < 1e-4 && (c0[1] - c1[1]).abs() < 1e-4);
}

#[test]
fn a_stack_and_a_clump_spread_without_throwing_particles() {
    // a wall-clipped corner (20 particles at one point) and a clump (20 on a circle of
    // 0.01 R), inside a lattice at rest spacing
    let r = 1.0;
    let rest = lattice(7, 0.5);
    let rho0 = kernel_density(&rest, r)
        .unwrap()
        .into_iter()
        .fold(0.0f32, f32::max);
    let mut x = rest.clone();
    x.extend(std::iter::repeat_n([0.0f32, 0.0], 20));
    x.extend((0..20).map(|k| {
        let a = k as f32 * std::f32::consts::TAU / 20.0;
        [1.5 + 0.01 * r * a.cos(), 1.5 + 0.01 * r * a.sin()]
    }));
    let orig = x.clone();
    let movable = vec![true; x.len()];
    let params = RelaxParams {
        radius: r,
        rest_density: rho0,
        iterations: 3,
        omega: 1.0,
    };
    let before = kernel_density(&x, r).unwrap();
    relax_density(&mut x, &movable, &params).unwrap();
    let after = kernel_density(&x, r).unwrap();
    let bound = params.iterations as f32 * MAX_MOVE * r * (1.0 + 1e-5);
    for (a, b) in x.iter().zip(&orig) {
        assert!(a.iter().all(|v| v.is_finite()));
        let m = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
        assert!(m <= bound, "moved {m} > {bound}");
    }
    // the stack separates: no two of its particles coincide any more
    let stack = &x[rest.len()..rest.len() + 20];
    for (k, a) in stack.iter().enumerate() {
        for b in &stack[k + 1..] {
            assert!(a != b, "still coincident at {a:?}");
        }
    }
    let peak = |v: &[f32]| v.iter().copied().fold(0.0f32, f32::max);
    assert!(
        peak(&after) < 0.8 * peak(&before),
        "{} -> {}",
        peak(&before),
        peak(&after)
    );
}

#[test]
fn immovable_particles_stay_and_bad_input_names_the_field() {
    let mut x = lattice(6, 0.5);
    let orig = x.clone();
    let movable: Vec<bool> = (0..x.len()).map(|i| i % 6 != 0).collect();
    let params = RelaxParams {
        radius: 2.0,
        rest_density: 2.0,
        iterations: 3,
        omega: 1.0,
    };
    relax_density(&mut x, &movable, &params).unwrap();
    for (i, (a, b)) in x.iter().zip(&orig).enumerate() {
        assert_eq!(movable[i], a != b, "particle {i}");
    }
    let field = |e: GraphError| match e {
        GraphError::InvalidInput { field, .. } => field,
    };
    let bad = [
        (
            RelaxParams {
                radius: 0.0,
                ..params
            },
            "radius",
        ),
        (
            RelaxParams {
                rest_density: f32::NAN,
                ..params
            },
            "rest_density",
        ),
        (
            RelaxParams {
                iterations: 101,
                ..params
            },
            "iterations",
        ),
        (
            RelaxParams {
                omega: 2.5,
                ..params
            },
            "omega",
        ),
    ];
    for (p, name) in bad {
        let mut y = orig.clone();
        assert_eq!(
            field(relax_density(&mut y, &movable, &p).unwrap_err()),
            name
        );
        assert_eq!(y, orig);
    }
    let mut y = orig.clone();
    assert_eq!(
        field(relax_density(&mut y, &movable[1..], &params).unwrap_err()),
        "movable"
    );
    y[3][0] = f32::NAN;
    assert_eq!(
        field(relax_density(&mut y, &movable, &params).unwrap_err()),
        "positions"
    );
}

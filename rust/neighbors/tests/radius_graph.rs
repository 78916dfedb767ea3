//! Radius graph against an O(N^2) brute force, plus edge cases.

use hybridmpm_neighbors::{
    Graph, GraphError, GraphParams, Neighbors, radius_graph, radius_graph_as,
};
use proptest::prelude::*;

/// O(N^2) reference with the documented criterion, order and cap rule.
fn brute<const D: usize>(pos: &[[f32; D]], params: &GraphParams) -> Graph<D> {
    let rr = params.radius * params.radius;
    let mut g = Graph::<D>::default();
    for (i, pi) in pos.iter().enumerate() {
        // (distance, sender, displacement)
        let mut cand: Vec<(f32, u32, [f32; D])> = Vec::new();
        for (j, pj) in pos.iter().enumerate() {
            if i == j && !params.self_edges {
                continue;
            }
            let mut d = [0.0f32; D];
            for k in 0..D {
                d[k] = pj[k] - pi[k];
            }
            let mut dd = d[0] * d[0];
            for x in &d[1..] {
                dd += x * x;
            }
            if dd <= rr {
                cand.push((dd.sqrt(), j as u32, d));
            }
        }
        if let Some(k) = params.max_neighbors {
            cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            if cand.len() > k {
                g.dropped += cand.len() - k;
                cand.truncate(k);
            }
            cand.sort_by_key(|c| c.1);
        }
        for (dist, j, d) in cand {
            g.senders.push(j);
            g.receivers.push(i as u32);
            g.displacement.push(d);
            g.distance.push(dist);
        }
    }
    g
}

fn check<const D: usize>(pos: &[[f32; D]], params: &GraphParams) {
    let got = radius_graph(pos, params).expect("valid input");
    let want = brute(pos, params);
    assert_eq!(
        got.num_edges(),
        want.num_edges(),
        "edge count, params {params:?}"
    );
    assert_eq!(got, want, "params {params:?}");
}

fn params_strategy(radius: impl Strategy<Value = f32>) -> impl Strategy<Value = GraphParams> {
    (radius, any::<bool>(), prop::option::of(1usize..12)).prop_map(
        |(radius, self_edges, max_neighbors)| GraphParams {
            radius,
            self_edges,
            max_neighbors,
            max_edges: None,
        },
    )
}

/// Float positions in a random box at a random offset.
fn float_cloud<const D: usize>() -> impl Strategy<Value = Vec<[f32; D]>> {
    (0usize..300, -1000.0f32..1000.0, 0.01f32..10.0).prop_flat_map(|(n, off, size)| {
        prop::collection::vec(
            prop::array::uniform::<_, D>((0.0f32..1.0).prop_map(move |x| off + size * x)),
            n,
        )
    })
}

/// Integer lattice points (many duplicates and exact distance ties).
fn int_cloud<const D: usize>() -> impl Strategy<Value = Vec<[f32; D]>> {
    prop::collection::vec(
        prop::array::uniform::<_, D>((-4i32..5).prop_map(|x| x as f32)),
        0..300,
    )
}

/// Brute-force check with the radius a fraction `frac` of the cloud's x extent.
fn check_fraction<const D: usize>(pos: &[[f32; D]], frac: f32, p: GraphParams) {
    let (lo, hi) = pos
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), q| (a.min(q[0]), b.max(q[0])));
    let extent = if pos.is_empty() {
        1.0
    } else {
        (hi - lo).max(1e-3)
    };
    check(
        pos,
        &GraphParams {
            radius: frac * extent,
            ..p
        },
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn float_2d(
        pos in float_cloud::<2>(),
        frac in 0.001f32..0.5,
        p in params_strategy(Just(1.0f32)),
    ) {
        check_fraction(&pos, frac, p);
    }

    #[test]
    fn float_3d(
        pos in float_cloud::<3>(),
        frac in 0.001f32..0.7,
        p in params_strategy(Just(1.0f32)),
    ) {
        check_fraction(&pos, frac, p);
    }

    #[test]
    fn lattice_2d(pos in int_cloud::<2>(), p in params_strategy((1i32..9).prop_map(|r| r as f32 * 0.5))) {
        check(&pos, &p);
    }

    #[test]
    fn lattice_3d(pos in int_cloud::<3>(), p in params_strategy((1i32..9).prop_map(|r| r as f32 * 0.5))) {
        check(&pos, &p);
    }

    /// Cluster plus one far outlier: the grid must stay small and correct.
    #[test]
    fn outlier_3d(
        pos in prop::collection::vec(prop::array::uniform::<_, 3>(0.0f32..1.0), 1..200),
        far in prop::array::uniform::<_, 3>(-1e30f32..1e30),
        p in params_strategy(0.01f32..0.5),
    ) {
        let mut pos = pos;
        pos.insert(pos.len() / 2, far);
        check(&pos, &p);
    }
}

#[test]
fn empty_input_is_empty_graph() {
    let g = radius_graph::<2>(&[], &GraphParams::default()).unwrap();
    assert!(g.is_empty());
    assert_eq!(g.dropped, 0);
    let g = radius_graph::<3>(
        &[],
        &GraphParams {
            max_neighbors: Some(3),
            ..Default::default()
        },
    )
    .unwrap();
    assert!(g.is_empty());
}

#[test]
fn duplicates_are_all_connected() {
    let pos = vec![[0.25f32, -3.0, 7.0]; 50];
    let p = GraphParams {
        radius: 1e-6,
        self_edges: true,
        max_neighbors: None,
        max_edges: None,
    };
    let g = radius_graph(&pos, &p).unwrap();
    assert_eq!(g.num_edges(), 50 * 50);
    assert!(g.distance.iter().all(|&d| d == 0.0));
    check(&pos, &p);
    let p = GraphParams {
        self_edges: false,
        max_neighbors: Some(7),
        ..p
    };
    let g = radius_graph(&pos, &p).unwrap();
    assert_eq!(g.num_edges(), 50 * 7);
    assert_eq!(g.dropped, 50 * (49 - 7));
    // Ties at distance 0 keep the lowest indices.
    assert_eq!(&g.senders[..7], &[1, 2, 3, 4, 5, 6, 7]);
    assert_eq!(&g.senders[7..14], &[0, 2, 3, 4, 5, 6, 7]);
    check(&pos, &p);
}

#[test]
fn single_far_outlier_keeps_graph_correct() {
    // 4096 lattice particles and one at 1e7: a grid of fixed cell size over
    // the bounding box would have ~1e18 cells.
    let mut pos: Vec<[f32; 2]> = (0..4096)
        .map(|i| [(i % 64) as f32 * 0.005, (i / 64) as f32 * 0.005])
        .collect();
    pos.push([1e7, -1e7]);
    for self_edges in [false, true] {
        let p = GraphParams {
            radius: 0.015,
            self_edges,
            max_neighbors: None,
            max_edges: None,
        };
        check(&pos, &p);
    }
}

#[test]
fn extreme_magnitudes() {
    // Huge radius: r*r overflows to inf, every pair is connected.
    let pos = [[3e38f32, -3e38], [-3e38, 3e38], [0.0, 0.0], [1.0, 1.0]];
    let p = GraphParams {
        radius: 1e30,
        self_edges: true,
        max_neighbors: None,
        max_edges: None,
    };
    assert_eq!(radius_graph(&pos, &p).unwrap().num_edges(), 16);
    check(&pos, &p);
    check(
        &pos,
        &GraphParams {
            max_neighbors: Some(2),
            ..p
        },
    );
    // Tiny radius and tiny separations (subnormal squares).
    let pos = [
        [0.0f32, 0.0],
        [1e-30, 0.0],
        [3e-23, 1e-23],
        [1e-20, 0.0],
        [-1e-38, 1e-45],
    ];
    for r in [1e-44f32, 1e-30, 1e-22, 2e-20] {
        check(
            &pos,
            &GraphParams {
                radius: r,
                self_edges: false,
                max_neighbors: None,
                max_edges: None,
            },
        );
    }
}

#[test]
fn cap_reports_dropped_and_sorted_senders() {
    // 1D-like row of points at unit spacing, radius 2.5: interior receivers
    // have 5 neighbours (incl. self); cap 3 keeps self and the two adjacent.
    let pos: Vec<[f32; 2]> = (0..10).map(|i| [i as f32, 0.0]).collect();
    let p = GraphParams {
        radius: 2.5,
        self_edges: true,
        max_neighbors: Some(3),
        max_edges: None,
    };
    let g = radius_graph(&pos, &p).unwrap();
    let of5: Vec<u32> = g
        .senders
        .iter()
        .zip(&g.receivers)
        .filter(|(_, r)| **r == 5)
        .map(|(s, _)| *s)
        .collect();
    assert_eq!(of5, vec![4, 5, 6]);
    let full = radius_graph(
        &pos,
        &GraphParams {
            max_neighbors: None,
            ..p
        },
    )
    .unwrap();
    assert_eq!(g.num_edges() + g.dropped, full.num_edges());
    check(&pos, &p);
}

#[test]
fn receivers_sorted_then_senders() {
    let pos: Vec<[f32; 3]> = (0..2000u32)
        .map(|i| {
            let h = i.wrapping_mul(2654435761);
            [
                (h % 97) as f32 * 0.01,
                (h % 89) as f32 * 0.01,
                (h % 83) as f32 * 0.01,
            ]
        })
        .collect();
    let g = radius_graph(
        &pos,
        &GraphParams {
            radius: 0.05,
            ..Default::default()
        },
    )
    .unwrap();
    for e in 1..g.num_edges() {
        let a = (g.receivers[e - 1], g.senders[e - 1]);
        let b = (g.receivers[e], g.senders[e]);
        assert!(a < b, "edge {e}: {a:?} !< {b:?}");
    }
}

fn jittered_lattice(n_side: usize, spacing: f32) -> Vec<[f32; 3]> {
    let mut v = Vec::with_capacity(n_side.pow(3));
    let mut s = 12345u32;
    for z in 0..n_side {
        for y in 0..n_side {
            for x in 0..n_side {
                let mut j = [0.0f32; 3];
                for c in &mut j {
                    s = s.wrapping_mul(1664525).wrapping_add(1013904223);
                    *c = ((s >> 8) as f32 / (1u32 << 24) as f32 - 0.5) * 0.2 * spacing;
                }
                v.push([
                    x as f32 * spacing + j[0],
                    y as f32 * spacing + j[1],
                    z as f32 * spacing + j[2],
                ]);
            }
        }
    }
    v
}

#[test]
fn one_and_two_threads_bitwise_equal() {
    let pos = jittered_lattice(24, 0.01);
    let pool1 = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let pool2 = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    for p in [
        GraphParams {
            radius: 0.025,
            self_edges: true,
            max_neighbors: None,
            max_edges: None,
        },
        GraphParams {
            radius: 0.025,
            self_edges: false,
            max_neighbors: Some(20),
            max_edges: None,
        },
    ] {
        let a = pool1.install(|| radius_graph(&pos, &p)).unwrap();
        let b = pool2.install(|| radius_graph(&pos, &p)).unwrap();
        assert!(a.num_edges() > 10 * pos.len());
        assert_eq!(a.senders, b.senders);
        assert_eq!(a.receivers, b.receivers);
        assert_eq!(a.dropped, b.dropped);
        let bits = |g: &Graph<3>| -> Vec<u32> {
            g.displacement
                .iter()
                .flatten()
                .chain(&g.distance)
                .map(|x| x.to_bits())
                .collect()
        };
        assert_eq!(bits(&a), bits(&b));
    }
}

#[test]
fn large_input_matches_brute_force() {
    // More than one rayon chunk of receivers.
    let pos = jittered_lattice(12, 0.01);
    check(
        &pos,
        &GraphParams {
            radius: 0.021,
            self_edges: true,
            max_neighbors: None,
            max_edges: None,
        },
    );
    check(
        &pos,
        &GraphParams {
            radius: 0.021,
            self_edges: false,
            max_neighbors: Some(9),
            max_edges: None,
        },
    );
}

#[test]
fn invalid_inputs_are_errors() {
    let ok = [[0.0f32, 0.0], [1.0, 1.0]];
    let field = |r: Result<Graph<2>, GraphError>| r.unwrap_err().field();
    let d = GraphParams::default();
    assert_eq!(field(radius_graph(&[[0.0, f32::NAN]], &d)), "positions");
    assert_eq!(
        field(radius_graph(&[[0.0, 0.0], [f32::INFINITY, 0.0]], &d)),
        "positions"
    );
    assert_eq!(
        field(radius_graph(&[[f32::NEG_INFINITY, 0.0]], &d)),
        "positions"
    );
    for radius in [
        0.0f32,
        -0.0,
        -1.0,
        f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
    ] {
        let p = GraphParams { radius, ..d };
        assert!(p.validate().is_err());
        assert_eq!(field(radius_graph(&ok, &p)), "radius", "radius {radius}");
        // Also with an empty input: parameters are validated first.
        assert!(radius_graph::<3>(&[], &p).is_err());
    }
    let p = GraphParams {
        max_neighbors: Some(0),
        ..d
    };
    assert_eq!(field(radius_graph(&ok, &p)), "max_neighbors");
    let msg = radius_graph(&[[0.0, f32::NAN]], &d)
        .unwrap_err()
        .to_string();
    assert!(msg.starts_with("positions:"), "{msg}");
    assert!(d.validate().is_ok());
    assert_eq!(d.radius, 0.015);
    assert!(d.self_edges);
    assert_eq!(d.max_neighbors, None);
}

#[test]
fn shuffled_order_matches_brute_force() {
    // Indices spatially incoherent: the neighbour lists span a wide index
    // range, so the comparison-sort path is used (lattice order uses the
    // bitmap path); both must give the same graph.
    let mut pos = jittered_lattice(14, 0.01);
    let n = pos.len();
    let mut s = 7u64;
    for i in (1..n).rev() {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        pos.swap(i, (s >> 33) as usize % (i + 1));
    }
    for p in [
        GraphParams {
            radius: 0.025,
            self_edges: true,
            max_neighbors: None,
            max_edges: None,
        },
        GraphParams {
            radius: 0.025,
            self_edges: false,
            max_neighbors: Some(25),
            max_edges: None,
        },
        GraphParams {
            radius: 0.015,
            self_edges: false,
            max_neighbors: None,
            max_edges: None,
        },
        GraphParams {
            radius: 0.015,
            self_edges: true,
            max_neighbors: Some(9),
            max_edges: None,
        },
    ] {
        check(&pos, &p);
    }
}

#[test]
fn write_into_caller_slices() {
    let pos = jittered_lattice(10, 0.01);
    let p = GraphParams {
        radius: 0.02,
        self_edges: false,
        max_neighbors: Some(12),
        max_edges: None,
    };
    let nb = Neighbors::search(&pos, &p).unwrap();
    let e = nb.num_edges();
    let want: Graph<3, i64> = radius_graph_as(&pos, &p).unwrap();
    let want_s = want.senders.clone();
    assert_eq!(nb.dropped(), want.dropped);
    let mut s = vec![-7i64; e];
    let mut r = vec![-7i64; e];
    let mut dp = vec![[f32::NAN; 3]; e];
    let mut ds = vec![f32::NAN; e];
    nb.write(&mut s, &mut r, &mut dp, &mut ds).unwrap();
    assert_eq!(
        (s, r, dp, ds),
        (
            want.senders,
            want.receivers,
            want.displacement,
            want.distance
        )
    );
    let mut short = vec![0i64; e - 1];
    let mut r = vec![0i64; e];
    let mut dp = vec![[0.0; 3]; e];
    let mut ds = vec![0.0; e];
    let err = nb.write(&mut short, &mut r, &mut dp, &mut ds).unwrap_err();
    assert_eq!(err.field(), "output");
    let u: Graph<3> = radius_graph(&pos, &p).unwrap();
    assert!(u.senders.iter().zip(&want_s).all(|(a, b)| *a as i64 == *b));
}

#[test]
fn parallel_path_matches_brute_force() {
    // Above the serial thresholds (8192 particles, 2^18 edges): chunks of
    // receivers cut cells, the write phase runs in parallel.
    let mut s = 3u32;
    let mut pos: Vec<[f32; 2]> = (0..96 * 96)
        .map(|i| {
            let mut j = [0.0f32; 2];
            for c in &mut j {
                s = s.wrapping_mul(1664525).wrapping_add(1013904223);
                *c = ((s >> 8) as f32 / (1u32 << 24) as f32 - 0.5) * 0.3;
            }
            [(i % 96) as f32 + j[0], (i / 96) as f32 + j[1]]
        })
        .collect();
    // Shuffle half of the particles so both index-coherent and incoherent
    // neighbourhoods occur.
    for i in (1..pos.len() / 2).rev() {
        s = s.wrapping_mul(1664525).wrapping_add(1013904223);
        pos.swap(i, (s >> 8) as usize % (i + 1));
    }
    let full = GraphParams {
        radius: 3.2,
        self_edges: true,
        max_neighbors: None,
        max_edges: None,
    };
    assert!(radius_graph(&pos, &full).unwrap().num_edges() > 1 << 18);
    check(&pos, &full);
    check(
        &pos,
        &GraphParams {
            radius: 3.2,
            self_edges: false,
            max_neighbors: Some(20),
            max_edges: None,
        },
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    /// The edge budget: a graph is refused (field "radius") iff it has more
    /// than `max_edges` edges, and is otherwise the graph without a budget.
    #[test]
    fn edge_budget_refuses_exactly_above_max_edges(
        pos in float_cloud::<2>(),
        frac in 0.001f32..0.7,
        p in params_strategy(Just(1.0f32)),
        slack in -3i64..3,
    ) {
        let extent = pos.iter().flatten().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-3);
        let p = GraphParams { radius: frac * extent, ..p };
        let full = radius_graph(&pos, &p).unwrap();
        let e = full.num_edges() as i64;
        let m = (e + slack).max(0) as usize;
        let got = radius_graph(&pos, &GraphParams { max_edges: Some(m), ..p });
        if full.num_edges() <= m {
            prop_assert_eq!(got.unwrap(), full);
        } else {
            let err = got.unwrap_err();
            prop_assert_eq!(err.field(), "radius");
            prop_assert!(err.to_string().contains(&format!("more than max_edges = {m} edges")), "{}", err);
        }
    }
}

#[test]
fn edge_budget_stops_a_huge_graph_early_on_any_thread_count() {
    // 12 000 points with radius 10 would give 1.44e8 edges (576 MB of sender
    // lists, 4 GB of edge arrays): refused after counting about a million.
    // (Kept below 1 GB should the budget ever be ignored; 30 000 points, the
    // case that aborted the process, is the Python test's, under a ulimit.)
    let mut s = 7u64;
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let pos: Vec<[f32; 2]> = (0..12_000).map(|_| [next(), next()]).collect();
    let p = GraphParams {
        radius: 10.0,
        max_edges: Some(1_000_000),
        ..Default::default()
    };
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let t0 = std::time::Instant::now();
        let err = match pool.install(|| Neighbors::search(&pos, &p)) {
            Err(e) => e,
            Ok(_) => panic!("a graph of 1.44e8 edges was accepted with max_edges = 1e6"),
        };
        assert_eq!(err.field(), "radius");
        let msg = err.to_string();
        assert!(msg.contains("more than max_edges = 1000000 edges"), "{msg}");
        // every point is a candidate of every other: the bound is N^2
        assert!(msg.contains("144000000 edges"), "{msg}");
        assert!(t0.elapsed().as_secs_f64() < 5.0, "{:?}", t0.elapsed());
    }
    // max_edges = 0 refuses any edge, and an empty cloud is always fine
    let p0 = GraphParams {
        max_edges: Some(0),
        ..Default::default()
    };
    assert!(radius_graph(&pos[..1], &p0).is_err());
    assert_eq!(radius_graph::<2>(&[], &p0).unwrap().num_edges(), 0);
}

#[test]
fn sparse_sheet_and_dense_clump_match_brute_force() {
    // A thin sheet spread over a tall bounding box (cells of one or two
    // particles: each receiver tests its rows directly, and the grid's cell
    // cap is reached) next to a dense clump (cells of many receivers: the
    // shared candidate list), shuffled so the accepted senders of a row come
    // out of order; with and without self-edges and a cap.
    let mut s = 11u64;
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let mut pos: Vec<[f32; 3]> = (0..900).map(|_| [next(), 0.02 * next(), next()]).collect();
    pos.extend((0..400).map(|_| {
        [
            0.5 + 0.05 * next(),
            0.9 + 0.05 * next(),
            0.5 + 0.05 * next(),
        ]
    }));
    let n = pos.len();
    for i in (1..n).rev() {
        let j = (next() * (i + 1) as f32) as usize % (i + 1);
        pos.swap(i, j);
    }
    for (self_edges, max_neighbors) in [(true, None), (false, None), (true, Some(7))] {
        check(
            &pos,
            &GraphParams {
                radius: 0.04,
                self_edges,
                max_neighbors,
                max_edges: None,
            },
        );
    }
}

//! The parameter structs' serde reading: defaults, face overrides,
//! unknown keys, colliders (`cargo test -p hybridmpm-mpm --features serde --lib params`).

use super::*;
use crate::collider::Shape;

#[test]
fn defaults_round_trip_and_fill_missing_keys() {
    let d = SolverParams::<3>::default();
    let json = serde_json::to_string(&d).unwrap();
    assert_eq!(serde_json::from_str::<SolverParams<3>>(&json).unwrap(), d);
    assert_eq!(serde_json::from_str::<SolverParams<3>>("{}").unwrap(), d);
    // f32 written shortest, so a reader in f64 gets the decimal default
    assert!(json.contains("\"cfl\":0.4,"), "{json}");
    assert!(!json.contains("faces"), "{json}");
}

#[test]
fn a_face_override_falls_back_to_the_all_faces_values() {
    let p: SolverParams<2> = serde_json::from_str(
        r#"{"walls": {"faces": {"y-": {"condition": "sticky"}, "x+": {}}, "friction": 0.25}}"#,
    )
    .unwrap();
    let w = &p.walls;
    assert_eq!(
        w.faces[1][0],
        Some(WallFace {
            condition: BoundaryCondition::Sticky,
            friction: 0.25
        })
    );
    assert_eq!(w.face(0, 1), w.face(0, 0));
    assert_eq!(w.faces[0][0], None);
    let back: SolverParams<2> = serde_json::from_str(&serde_json::to_string(&p).unwrap()).unwrap();
    assert_eq!(back, p);
}

#[test]
fn unknown_keys_and_faces_are_refused() {
    for (json, word) in [
        (r#"{"wter": {}}"#, "wter"),
        (r#"{"water": {"bulk": 1}}"#, "bulk"),
        (r#"{"walls": {"faces": {"w-": {}}}}"#, "w-"),
        (r#"{"walls": {"faces": {"y-": {"mu": 1}}}}"#, "mu"),
        (r#"{"gravity": [0, -9.8, 0]}"#, "2 numbers"),
        (r#"{"walls": {"condition": "glue"}}"#, "glue"),
    ] {
        let e = serde_json::from_str::<SolverParams<2>>(json).unwrap_err();
        assert!(e.to_string().contains(word), "{json}: {e}");
    }
}

#[test]
fn colliders_build_in_their_dimension() {
    let c: ColliderParams = serde_json::from_str(
        r#"{"shape": "box", "center": [0.5, 0.2], "half_extents": [0.1, 0.05], "angle_deg": 90}"#,
    )
    .unwrap();
    assert_eq!(c.condition, BoundaryCondition::Separate);
    let Shape::Box { rotation, .. } = c.build::<2>("colliders[0]").unwrap().shape else {
        panic!("not a box");
    };
    assert!((rotation[(1, 0)] - 1.0).abs() < 1e-6);
    let e = c.build::<3>("colliders[0]").unwrap_err().to_string();
    assert!(e.starts_with("colliders[0].center"), "{e}");
    let s: ColliderParams =
        serde_json::from_str(r#"{"shape": "circle", "center": [0.5, 0.2]}"#).unwrap();
    let e = s.build::<2>("colliders[1]").unwrap_err().to_string();
    assert!(e.starts_with("colliders[1].radius: missing"), "{e}");
    assert_eq!(
        serde_json::to_string(&ColliderParams::default()).unwrap(),
        r#"{"condition":"separate","friction":0.0,"project":true}"#
    );
}

/// A parameter set is named by its material, the one key of a dict (serde's
/// externally tagged form, what Python's `MpmParams.to_dict` writes);
/// unknown keys inside it, an unknown material, and a dict of no material
/// or of two are refused.
#[test]
fn a_set_is_a_dict_of_one_material() {
    let jelly = MaterialParams::Elastic(ElasticParams {
        youngs_modulus: 5.0e4,
        ..Default::default()
    });
    let p = SolverParams::<2> {
        sets: vec![jelly, MaterialParams::Water(WaterParams::default())],
        ..Default::default()
    };
    let json = serde_json::to_value(&p).unwrap();
    assert_eq!(
        json["sets"],
        serde_json::json!([
            {"elastic": {"density": 1000.0, "youngs_modulus": 5.0e4, "poisson_ratio": 0.3f32, "model": "corotated"}},
            {"water": {"density": 1000.0, "bulk_modulus": 4.0e5, "viscosity": 0.0}},
        ])
    );
    assert_eq!(serde_json::from_value::<SolverParams<2>>(json).unwrap(), p);
    for (json, word) in [
        (r#"{"sets": [{"elastic": {"youngs": 1}}]}"#, "youngs"),
        (r#"{"sets": [{"jelly": {}}]}"#, "jelly"),
        (r#"{"sets": [{}]}"#, ""),
        (r#"{"sets": [{"water": {}, "sand": {}}]}"#, ""),
    ] {
        assert!(
            serde_json::from_str::<SolverParams<2>>(json)
                .unwrap_err()
                .to_string()
                .contains(word)
        );
    }
}

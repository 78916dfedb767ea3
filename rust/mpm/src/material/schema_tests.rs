//! The material schema against the structs it describes: the names and
//! order of the serde keys, and every bound of every parameter checked by
//! `validate()` (`cargo test -p hybridmpm-mpm --features serde --lib schema`).

use super::schema::{Limit, MaterialSchema, Param, ParamValue};
use super::*;

/// A parameter set of `model` with `name` set to `value` (the rest default).
fn set_with(model: &str, name: &str, value: f32) -> MaterialParams {
    let json = serde_json::json!({ model: { name: value } });
    serde_json::from_value(json).unwrap()
}

#[test]
fn each_table_lists_its_structs_fields_in_order() {
    for (material, params, defaults) in material_schema() {
        let default = MaterialParams::default_for(material);
        let text = serde_json::to_string(&default).unwrap();
        let set: serde_json::Value = serde_json::from_str(&text).unwrap();
        let mut keys: Vec<&String> = set[material.name()].as_object().unwrap().keys().collect();
        // the keys in the order serde writes them, the struct's
        keys.sort_by_key(|k| text.find(&format!("\"{k}\":")).unwrap());
        let names: Vec<&str> = params.iter().map(|p| p.name).collect();
        assert_eq!(keys, names, "{}", material.name());
        assert_eq!(defaults.len(), params.len());
        for (p, d) in params.iter().zip(&defaults) {
            let given = &set[material.name()][p.name];
            match d {
                ParamValue::Number(x) => {
                    assert_eq!(given.as_f64().map(|g| g as f32), Some(*x), "{}", p.name)
                }
                ParamValue::Name(n) => assert_eq!(given.as_str(), Some(*n), "{}", p.name),
            }
            p.check("default", *d).unwrap();
        }
    }
}

/// The f32 just outside `limit` (the bound itself when it is exclusive)
/// and the one just inside, toward `inward` (+1 above a lower bound).
fn around(limit: Limit, inward: f32) -> (f32, f32) {
    let b = limit.value as f32;
    let step = |x: f32, up: bool| if up { x.next_up() } else { x.next_down() };
    if limit.inclusive {
        (step(b, inward < 0.0), b)
    } else {
        (b, step(b, inward > 0.0))
    }
}

#[test]
fn every_bound_of_every_parameter_is_checked_naming_the_field() {
    let mut bounds = 0;
    for (material, params, _) in material_schema() {
        let model = material.name();
        let numbers = params.iter().filter(|p| p.choices.is_empty());
        for p in numbers {
            let sides = [(p.lower, 1.0), (p.upper, -1.0)];
            for (limit, inward) in sides.into_iter().filter_map(|(l, s)| Some((l?, s))) {
                bounds += 1;
                let (outside, inside) = around(limit, inward);
                let field = format!("sets[0].{model}.{}", p.name);
                let e = set_with(model, p.name, outside)
                    .validate("sets[0]")
                    .unwrap_err()
                    .to_string();
                assert!(e.starts_with(&format!("{field}: must be ")), "{e}");
                assert!(e.contains(&p.range_text()), "{e}");
                set_with(model, p.name, inside)
                    .validate("sets[0]")
                    .unwrap_or_else(|e| panic!("{field} = {inside}: {e}"));
            }
            // (JSON has no NaN: the checker `validate` calls, directly)
            let e = p.check("x", ParamValue::Number(f32::NAN)).unwrap_err();
            assert_eq!(e.to_string(), "x: must be finite, got NaN");
        }
    }
    assert!(bounds >= 20, "{bounds} bounds");
}

#[test]
fn a_range_reads_as_its_bounds() {
    let nu = ElasticParams::PARAMS
        .iter()
        .find(|p| p.name == "poisson_ratio");
    let nu: &Param = nu.unwrap();
    assert_eq!(nu.key(), "nu");
    assert_eq!(nu.range_text(), "in [0, 0.5)");
    assert!(nu.contains(0.0) && !nu.contains(0.5) && !nu.contains(f64::NAN));
    let e = ElasticParams {
        poisson_ratio: 0.5,
        ..Default::default()
    };
    let msg = e.validate().unwrap_err().to_string();
    assert_eq!(msg, "elastic.poisson_ratio: must be in [0, 0.5), got 0.5");
}

/// The shared P-wave speed at `stiffen = 1` gives the bits of
/// `sqrt((λ + 2μ)/ρ)` (`x·1 = x` exactly), so sand's CFL bound is unchanged.
#[test]
fn the_p_wave_speed_unstiffened_is_the_plain_formula_to_the_bit() {
    let mut seed = 0x9e37_79b9_u32;
    let mut next = || {
        seed ^= seed << 13;
        seed ^= seed >> 17;
        seed ^= seed << 5;
        seed as f32 / u32::MAX as f32
    };
    for _ in 0..10_000 {
        let (e, nu, rho) = (
            10f32.powf(9.0 * next()),
            0.499 * next(),
            1.0 + 3000.0 * next(),
        );
        let (mu, la) = lame(e, nu);
        let plain = ((la + 2.0 * mu) / rho).sqrt();
        assert_eq!(p_wave(e, nu, rho, 1.0).to_bits(), plain.to_bits());
    }
}

//! The registry's list against what is made of it: the codes, the names,
//! the schema's tables and `SolverParams`' default sets agree, in one
//! order (`cargo test -p hybridmpm-mpm --lib registry`).

use super::{Material, MaterialParams, Model, material_schema};
use crate::params::{BASE_SETS, SolverParams};

#[test]
fn the_codes_are_0_to_n_in_the_lists_order() {
    let n = Material::ALL.len();
    assert_eq!(BASE_SETS, n);
    for (i, &m) in Material::ALL.iter().enumerate() {
        assert_eq!(m as usize, i, "{m:?}");
        assert_eq!(Material::from_code(i as i64), Some(m));
    }
    assert_eq!(Material::from_code(n as i64), None);
    assert_eq!(Material::from_code(-1), None);
}

#[test]
fn the_names_are_the_variants_in_lowercase_and_distinct() {
    let names: Vec<&str> = Material::ALL.iter().map(|m| m.name()).collect();
    for (m, name) in Material::ALL.iter().zip(&names) {
        assert_eq!(*name, format!("{m:?}").to_lowercase());
    }
    let mut sorted = names.clone();
    sorted.sort_unstable();
    sorted.dedup();
    assert_eq!(sorted.len(), names.len(), "{names:?}");
}

#[test]
fn the_schema_and_the_default_table_list_every_material_by_code() {
    let schema: Vec<Material> = material_schema().iter().map(|row| row.0).collect();
    assert_eq!(schema, Material::ALL);
    let p = SolverParams::<2>::default();
    let table = p.table();
    let materials: Vec<Material> = table.iter().map(MaterialParams::material).collect();
    assert_eq!(materials, Material::ALL);
    for (set, (_, params, defaults)) in table.iter().zip(material_schema()) {
        assert!(set.density() > 0.0);
        set.validate("sets[0]").unwrap();
        assert_eq!(params.len(), defaults.len());
    }
}

#[test]
fn a_solid_carries_f() {
    let table = SolverParams::<3>::default().table();
    for (set, m) in table.iter().zip(Material::ALL) {
        let model = Model::new::<3>(set);
        assert!(!m.is_solid() || model.has_f(), "{m:?}");
    }
    let solids: Vec<Material> = Material::ALL.into_iter().filter(|m| m.is_solid()).collect();
    assert_eq!(
        solids,
        [Material::Elastic, Material::Snow, Material::Viscoplastic]
    );
}

/// The dict names a set by its material's name (serde's tag).
#[cfg(feature = "serde")]
#[test]
fn a_sets_tag_in_the_dict_is_its_materials_name() {
    for set in SolverParams::<2>::default().table() {
        let value = serde_json::to_value(&set).unwrap();
        let keys: Vec<&String> = value.as_object().unwrap().keys().collect();
        assert_eq!(keys, [set.material().name()]);
    }
}

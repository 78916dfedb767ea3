//! The walls of the domain: a band of cells inside each face with the
//! face's boundary condition, and (`serde` feature) their dict form with
//! face overrides by name.

use super::{BoundaryCondition, non_negative};
use crate::error::{MpmError, Result};

/// Boundary condition and Coulomb friction of one face of the domain walls.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WallFace {
    pub condition: BoundaryCondition,
    /// Coulomb friction coefficient μ (≥ 0; used with `Separate`).
    pub friction: f32,
}

/// The walls of the unit domain `[0, 1]^D`: a band of `cells` grid cells
/// inside each face, whose grid nodes get the face's boundary condition
/// with the face's inward normal.
///
/// `condition` and `friction` apply to every face; `faces` overrides them
/// face by face. Faces are named by axis and side: `x-` (x = 0), `x+`
/// (x = 1), `y-` (the floor: y is up, gravity points to −y), `y+` (the
/// ceiling), `z-`, `z+` (3D only). A rough floor with slipping side walls,
/// the usual granular-collapse setup, is `condition = Separate`,
/// `friction = 0` and `faces[1][0] = Some(WallFace { condition: Separate,
/// friction: μ })`.
///
/// In the parameter dict (`serde` feature) `faces` maps a face name to
/// `{"condition": ..., "friction": ...}`; a key the face leaves out takes
/// the all-faces value, and only overridden faces are written.
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(
    feature = "serde",
    derive(serde::Serialize, serde::Deserialize),
    serde(from = "wire::Walls", into = "wire::Walls")
)]
pub struct WallParams {
    /// Thickness of the wall band in grid cells, in [2, n_grid/4).
    pub cells: usize,
    /// Condition of every face without an override.
    pub condition: BoundaryCondition,
    /// Coulomb friction coefficient μ of every face without an override
    /// (used with `Separate`).
    pub friction: f32,
    /// Per-face overrides `faces[axis][side]` (side 0: the lower face `x-`,
    /// `y-`, `z-`; side 1: the upper face); `None` uses `condition` and
    /// `friction`. The z row must stay `None` in 2D.
    pub faces: [[Option<WallFace>; 2]; 3],
}

impl Default for WallParams {
    fn default() -> Self {
        WallParams {
            cells: 3,
            condition: BoundaryCondition::Separate,
            friction: 0.0,
            faces: [[None; 2]; 3],
        }
    }
}

impl WallParams {
    /// Face names by `[axis][side]`.
    pub const FACE_NAMES: [[&'static str; 2]; 3] = [["x-", "x+"], ["y-", "y+"], ["z-", "z+"]];

    /// `(axis, side)` of a face name (`"x-"`, ..., `"z+"`), or `None`.
    pub fn face_index(name: &str) -> Option<(usize, usize)> {
        (0..3)
            .flat_map(|a| (0..2).map(move |s| (a, s)))
            .find(|&(a, s)| Self::FACE_NAMES[a][s] == name)
    }

    /// The condition and friction in force on face `(axis, side)`.
    pub fn face(&self, axis: usize, side: usize) -> WallFace {
        self.faces[axis][side].unwrap_or(WallFace {
            condition: self.condition,
            friction: self.friction,
        })
    }

    /// Checks the band thickness and every friction coefficient (errors
    /// name the field, e.g. `walls.faces.y-.friction`).
    pub fn validate(&self, n_grid: usize) -> Result<()> {
        if self.cells < 2 || 4 * self.cells >= n_grid {
            return Err(MpmError::invalid(
                "walls.cells",
                format!("must be in [2, n_grid/4), got {}", self.cells),
            ));
        }
        non_negative("walls.friction", self.friction)?;
        for (axis, row) in self.faces.iter().enumerate() {
            for (side, face) in row.iter().enumerate() {
                if let Some(f) = face {
                    let name = Self::FACE_NAMES[axis][side];
                    non_negative(&format!("walls.faces.{name}.friction"), f.friction)?;
                }
            }
        }
        Ok(())
    }
}

/// The dict form of [`WallParams`] (`serde` feature): its face overrides
/// by name.
#[cfg(feature = "serde")]
mod wire {
    use std::fmt;

    use serde::de::{self, DeserializeSeed, MapAccess, Visitor};
    use serde::ser::SerializeMap;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    use super::{BoundaryCondition, WallFace, WallParams};

    /// [`WallParams`] as written: a face override keeps the keys it leaves
    /// out (`None`) until the all-faces values are known.
    #[derive(Serialize, Deserialize)]
    #[serde(default, deny_unknown_fields, rename = "WallParams")]
    pub struct Walls {
        cells: usize,
        condition: BoundaryCondition,
        friction: f32,
        #[serde(skip_serializing_if = "Faces::is_empty")]
        faces: Faces,
    }

    impl Default for Walls {
        fn default() -> Self {
            WallParams::default().into()
        }
    }

    #[derive(Clone, Copy, Default, Serialize, Deserialize)]
    #[serde(default, deny_unknown_fields, rename = "WallFace")]
    struct Face {
        #[serde(skip_serializing_if = "Option::is_none")]
        condition: Option<BoundaryCondition>,
        #[serde(skip_serializing_if = "Option::is_none")]
        friction: Option<f32>,
    }

    /// Face overrides by `[axis][side]`, written as a map keyed by
    /// [`WallParams::FACE_NAMES`].
    #[derive(Default)]
    struct Faces([[Option<Face>; 2]; 3]);

    /// [`WallParams::FACE_NAMES`] in one list (for error messages).
    static FACE_LIST: [&str; 6] = {
        let n = WallParams::FACE_NAMES;
        [n[0][0], n[0][1], n[1][0], n[1][1], n[2][0], n[2][1]]
    };

    impl Faces {
        fn is_empty(&self) -> bool {
            self.0.iter().flatten().all(Option::is_none)
        }
    }

    impl Serialize for Faces {
        fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
            let mut map = s.serialize_map(None)?;
            for (names, row) in WallParams::FACE_NAMES.iter().zip(&self.0) {
                for (name, face) in names.iter().zip(row) {
                    if let Some(face) = face {
                        map.serialize_entry(name, face)?;
                    }
                }
            }
            map.end()
        }
    }

    impl<'de> Deserialize<'de> for Faces {
        fn deserialize<De: Deserializer<'de>>(d: De) -> Result<Self, De::Error> {
            d.deserialize_map(FacesVisitor)
        }
    }

    struct FacesVisitor;

    impl<'de> Visitor<'de> for FacesVisitor {
        type Value = Faces;

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("a map of wall face name to {condition, friction}")
        }

        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Faces, A::Error> {
            let mut faces = Faces::default();
            while let Some((axis, side)) = map.next_key_seed(FaceName)? {
                faces.0[axis][side] = Some(map.next_value()?);
            }
            Ok(faces)
        }
    }

    /// A face name read as `(axis, side)`; any other name is an unknown field.
    struct FaceName;

    impl<'de> DeserializeSeed<'de> for FaceName {
        type Value = (usize, usize);

        fn deserialize<De: Deserializer<'de>>(self, d: De) -> Result<Self::Value, De::Error> {
            d.deserialize_identifier(self)
        }
    }

    impl<'de> Visitor<'de> for FaceName {
        type Value = (usize, usize);

        fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
            f.write_str("a wall face name")
        }

        fn visit_str<E: de::Error>(self, v: &str) -> Result<Self::Value, E> {
            WallParams::face_index(v).ok_or_else(|| E::unknown_field(v, &FACE_LIST))
        }
    }

    impl From<Walls> for WallParams {
        fn from(w: Walls) -> Self {
            let faces = w.faces.0.map(|row| {
                row.map(|face| {
                    face.map(|f| WallFace {
                        condition: f.condition.unwrap_or(w.condition),
                        friction: f.friction.unwrap_or(w.friction),
                    })
                })
            });
            WallParams {
                cells: w.cells,
                condition: w.condition,
                friction: w.friction,
                faces,
            }
        }
    }

    impl From<WallParams> for Walls {
        fn from(w: WallParams) -> Self {
            let faces = w.faces.map(|row| {
                row.map(|face| {
                    face.map(|f| Face {
                        condition: Some(f.condition),
                        friction: Some(f.friction),
                    })
                })
            });
            Walls {
                cells: w.cells,
                condition: w.condition,
                friction: w.friction,
                faces: Faces(faces),
            }
        }
    }
}

//! Typed access to JSON fields with errors that name the file, the field path and what was
//! expected.

use std::path::{Path, PathBuf};

use gausmoke_core::glam::{Mat4, Vec3};
use serde_json::Value;

use crate::dataset::{Aabb, Obstacle};
use crate::error::{DataError, Result, io_err};

pub(crate) fn read_json(path: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    serde_json::from_str(&text).map_err(|source| DataError::Json {
        path: path.to_path_buf(),
        source,
    })
}

/// A JSON value together with the file it came from and its path inside the document.
#[derive(Clone, Copy)]
pub(crate) struct Node<'a> {
    pub file: &'a Path,
    pub value: &'a Value,
    field: &'a str,
}

/// Field paths are built as owned strings; this wrapper keeps them alive for the children.
pub(crate) struct Owned<'a> {
    file: &'a Path,
    value: &'a Value,
    field: String,
}

impl<'a> Owned<'a> {
    pub fn node(&self) -> Node<'_> {
        Node {
            file: self.file,
            value: self.value,
            field: &self.field,
        }
    }
}

impl<'a> Node<'a> {
    pub fn root(file: &'a Path, value: &'a Value) -> Self {
        Node {
            file,
            value,
            field: "",
        }
    }

    pub fn field_path(&self) -> &str {
        if self.field.is_empty() {
            "<root>"
        } else {
            self.field
        }
    }

    pub fn err(&self, expected: impl Into<String>) -> DataError {
        DataError::Field {
            path: self.file.to_path_buf(),
            field: self.field_path().to_string(),
            expected: expected.into(),
        }
    }

    fn child_name(&self, key: &str) -> String {
        if self.field.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.field)
        }
    }

    /// A required object member.
    pub fn get(&self, key: &str) -> Result<Owned<'a>> {
        let field = self.child_name(key);
        let obj = self
            .value
            .as_object()
            .ok_or_else(|| self.err(format!("an object with a `{key}` member")))?;
        match obj.get(key) {
            Some(value) => Ok(Owned {
                file: self.file,
                value,
                field,
            }),
            None => Err(DataError::Field {
                path: self.file.to_path_buf(),
                field,
                expected: "this field to be present".into(),
            }),
        }
    }

    /// An optional object member (`None` when absent or null).
    pub fn get_opt(&self, key: &str) -> Result<Option<Owned<'a>>> {
        let obj = self
            .value
            .as_object()
            .ok_or_else(|| self.err(format!("an object (looking for `{key}`)")))?;
        Ok(obj.get(key).filter(|v| !v.is_null()).map(|value| Owned {
            file: self.file,
            value,
            field: self.child_name(key),
        }))
    }

    pub fn array(&self) -> Result<Vec<Owned<'a>>> {
        let items = self.value.as_array().ok_or_else(|| self.err("an array"))?;
        Ok(items
            .iter()
            .enumerate()
            .map(|(i, value)| Owned {
                file: self.file,
                value,
                field: format!("{}[{i}]", self.field_path()),
            })
            .collect())
    }

    pub fn f64(&self) -> Result<f64> {
        self.value
            .as_f64()
            .filter(|v| v.is_finite())
            .ok_or_else(|| self.err("a finite number"))
    }

    pub fn positive_f64(&self) -> Result<f64> {
        let v = self.f64()?;
        if v > 0.0 {
            Ok(v)
        } else {
            Err(self.err(format!("a positive number (got {v})")))
        }
    }

    pub fn usize(&self) -> Result<usize> {
        self.value
            .as_u64()
            .and_then(|v| usize::try_from(v).ok())
            .ok_or_else(|| self.err("a non-negative integer"))
    }

    pub fn str(&self) -> Result<&'a str> {
        self.value.as_str().ok_or_else(|| self.err("a string"))
    }

    /// A fixed-length array of finite numbers.
    pub fn f64_array<const N: usize>(&self) -> Result<[f64; N]> {
        let expected = || format!("an array of {N} finite numbers");
        let items = self.value.as_array().ok_or_else(|| self.err(expected()))?;
        if items.len() != N {
            return Err(self.err(format!("{} (got {} entries)", expected(), items.len())));
        }
        let mut out = [0.0; N];
        for (o, v) in out.iter_mut().zip(items) {
            *o = v
                .as_f64()
                .filter(|x| x.is_finite())
                .ok_or_else(|| self.err(expected()))?;
        }
        Ok(out)
    }

    /// A 4x4 matrix given as a list of 4 rows (NeRF convention), returned as a glam matrix.
    pub fn mat4_rows(&self) -> Result<Mat4> {
        let expected = "a 4x4 matrix as 4 rows of 4 finite numbers";
        let rows = self.value.as_array().ok_or_else(|| self.err(expected))?;
        if rows.len() != 4 {
            return Err(self.err(format!("{expected} (got {} rows)", rows.len())));
        }
        let mut m = [[0.0f32; 4]; 4];
        for (r, row) in rows.iter().enumerate() {
            let row = row
                .as_array()
                .filter(|row| row.len() == 4)
                .ok_or_else(|| self.err(format!("{expected} (row {r} is not 4 numbers)")))?;
            for (c, v) in row.iter().enumerate() {
                m[r][c] = v
                    .as_f64()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| self.err(format!("{expected} (entry [{r}][{c}])")))?
                    as f32;
            }
        }
        // glam takes columns; the JSON lists rows.
        Ok(Mat4::from_cols_array_2d(&m).transpose())
    }

    pub fn file_buf(&self) -> PathBuf {
        self.file.to_path_buf()
    }
}

/// An optional `aabb` of `root`: `[[min x, y, z], [max x, y, z]]` in world units (nerfstudio's
/// key; the D-NeRF loader reads it too).
pub(crate) fn read_aabb(root: Node<'_>) -> Result<Option<Aabb>> {
    let Some(owned) = root.get_opt("aabb")? else {
        return Ok(None);
    };
    let node = owned.node();
    let rows = node.array()?;
    if rows.len() != 2 {
        return Err(node.err("[[min x, y, z], [max x, y, z]]"));
    }
    let min = rows[0].node().f64_array::<3>()?;
    let max = rows[1].node().f64_array::<3>()?;
    let (min, max) = (
        Vec3::new(min[0] as f32, min[1] as f32, min[2] as f32),
        Vec3::new(max[0] as f32, max[1] as f32, max[2] as f32),
    );
    if !(min.cmplt(max).all()) {
        return Err(node.err("a box whose min is below its max on every axis"));
    }
    Ok(Some(Aabb { min, max }))
}

/// `obstacles` (ours, optional): a list of `{"sphere": {"centre": [x, y, z], "radius": r}}`
/// and `{"box": {"min": [x, y, z], "max": [x, y, z]}}`, in world units.
pub(crate) fn read_obstacles(root: Node<'_>) -> Result<Vec<Obstacle>> {
    let Some(list) = root.get_opt("obstacles")? else {
        return Ok(Vec::new());
    };
    let mut obstacles = Vec::new();
    for item in list.node().array()? {
        let item = item.node();
        let finite = |node: Node<'_>, name: &str| -> Result<Vec3> {
            let v = node.get(name)?.node().f64_array::<3>()?;
            if v.iter().any(|x| !x.is_finite()) {
                return Err(node.err(format!("a finite {name}")));
            }
            Ok(Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32))
        };
        if let Some(sphere) = item.get_opt("sphere")? {
            let sphere = sphere.node();
            obstacles.push(Obstacle::Sphere {
                centre: finite(sphere, "centre")?,
                radius: sphere.get("radius")?.node().positive_f64()? as f32,
            });
        } else if let Some(cuboid) = item.get_opt("box")? {
            let cuboid = cuboid.node();
            let (min, max) = (finite(cuboid, "min")?, finite(cuboid, "max")?);
            if !min.cmplt(max).all() {
                return Err(cuboid.err("a box whose min is below its max on every axis"));
            }
            obstacles.push(Obstacle::Box { min, max });
        } else {
            return Err(item.err("a \"sphere\" or a \"box\""));
        }
    }
    Ok(obstacles)
}

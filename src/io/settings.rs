//! Configuration as data: configuration structs read from TOML or JSON files, changed by
//! `key.path=value` assignments, written back as TOML, and recorded with the provenance of a
//! run.
//!
//! Every configuration struct of the library (`SlamConfig`, `OdometryConfig`, ...) derives
//! serde with `#[serde(default, deny_unknown_fields)]`: a file may give any subset of the keys
//! (the others keep their defaults) and a key the struct does not have is an error that names
//! it with its full path (`odometry.estimatr`). Enums are written in lower case
//! (`estimator = "huber"`), the same names as the command line's values.
//!
//! The layers are applied onto a value tree ([`serde_json::Value`]) and the result is
//! deserialised once, so every value is checked by the struct's own types:
//!
//! ```
//! use rgbid::io::settings::{apply_assignments, Assignment};
//! use rgbid::odometry::{Estimator, OdometryConfig};
//!
//! let set: Assignment = "estimator=huber".parse()?;
//! let config = apply_assignments(&OdometryConfig::default(), &[set])?;
//! assert_eq!(config.estimator, Estimator::Huber);
//!
//! let typo: Assignment = "estimatr=huber".parse()?;
//! let err = apply_assignments(&OdometryConfig::default(), &[typo]).unwrap_err();
//! assert!(err.to_string().contains("estimatr"));
//! # Ok::<(), rgbid::io::settings::SettingsError>(())
//! ```
//!
//! Numbers that are not finite (`inf`) have no JSON form: such a value can be given on the
//! command line where a command has a flag for it, not in a file or an assignment.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::{Map, Value};

use crate::gpu::ComputeBackend;

/// Errors of configuration loading, naming the file or assignment and the key.
#[derive(Debug, thiserror::Error)]
pub enum SettingsError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The file's extension is neither `.toml` nor `.json`.
    #[error("{path}: a configuration file must end in .toml or .json")]
    Format {
        /// The file.
        path: PathBuf,
    },
    /// The file is not valid TOML or JSON.
    #[error("{path}: {message}")]
    Syntax {
        /// The file.
        path: PathBuf,
        /// The parser's message (with line and column).
        message: String,
    },
    /// A key the configuration does not have.
    #[error("{origin}: unknown key `{key}`{expected}")]
    UnknownKey {
        /// Where the key came from (a file, or `--set`).
        origin: String,
        /// The key's full path (`odometry.estimatr`).
        key: String,
        /// The keys allowed at that place, when known (`; expected one of ...`).
        expected: String,
    },
    /// A value of the wrong type or out of the allowed names.
    #[error("{origin}: `{key}`: {message}")]
    Invalid {
        /// Where the value came from (a file, or `--set`).
        origin: String,
        /// The key's full path (empty for the whole configuration).
        key: String,
        /// What is wrong.
        message: String,
    },
    /// A malformed `key.path=value` assignment, or a path that leads through a value that
    /// has no keys.
    #[error("--set {assignment}: {why}")]
    Assignment {
        /// The assignment as given.
        assignment: String,
        /// What is wrong with it.
        why: String,
    },
    /// The configuration could not be turned into a value tree or into TOML.
    #[error("configuration could not be written: {0}")]
    Serialize(String),
    /// A sidecar file could not be written.
    #[error(transparent)]
    Write(#[from] super::IoError),
}

/// File format of a configuration file, chosen by its extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// `.toml`
    Toml,
    /// `.json`
    Json,
}

impl Format {
    /// The format of `path` by its extension (case-insensitive).
    pub fn of(path: &Path) -> Result<Format, SettingsError> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("toml") => Ok(Format::Toml),
            Some("json") => Ok(Format::Json),
            _ => Err(SettingsError::Format {
                path: path.to_path_buf(),
            }),
        }
    }
}

/// One `key.path=value` assignment (the command line's `--set`).
///
/// The value is read as a TOML value (`3`, `0.5`, `true`, `"text"`, `[6, 8, 10]`); anything
/// that is not one is taken as a string, so `estimator=huber` needs no quotes. `null` sets an
/// optional value to none. Path segments are struct keys, or indices into lists.
#[derive(Clone, Debug, PartialEq)]
pub struct Assignment {
    /// The text as given.
    pub text: String,
    /// The key path, split at the dots.
    pub path: Vec<String>,
    /// The value.
    pub value: Value,
}

impl FromStr for Assignment {
    type Err = SettingsError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = |why: &str| SettingsError::Assignment {
            assignment: s.to_string(),
            why: why.to_string(),
        };
        let (key, raw) = s
            .split_once('=')
            .ok_or_else(|| bad("expected KEY.PATH=VALUE"))?;
        let path: Vec<String> = key
            .trim()
            .split('.')
            .map(|p| p.trim().to_string())
            .collect();
        if path.iter().any(String::is_empty) {
            return Err(bad("empty key in the path"));
        }
        let raw = raw.trim();
        let value = if raw == "null" {
            Value::Null
        } else {
            match toml::from_str::<toml::Table>(&format!("v = {raw}")) {
                Ok(mut t) => match t.remove("v") {
                    Some(v) => toml_to_json(v).map_err(|why| bad(&why))?,
                    None => Value::String(raw.to_string()),
                },
                Err(_) => Value::String(raw.to_string()),
            }
        };
        Ok(Assignment {
            text: s.to_string(),
            path,
            value,
        })
    }
}

/// A TOML value as a JSON value; non-finite floats and dates have no JSON form.
fn toml_to_json(v: toml::Value) -> Result<Value, String> {
    Ok(match v {
        toml::Value::String(s) => Value::String(s),
        toml::Value::Integer(i) => Value::from(i),
        toml::Value::Float(f) => {
            if !f.is_finite() {
                return Err(format!("{f} is not a finite number"));
            }
            Value::from(f)
        }
        toml::Value::Boolean(b) => Value::Bool(b),
        toml::Value::Datetime(d) => Value::String(d.to_string()),
        toml::Value::Array(a) => {
            Value::Array(a.into_iter().map(toml_to_json).collect::<Result<_, _>>()?)
        }
        toml::Value::Table(t) => Value::Object(
            t.into_iter()
                .map(|(k, v)| toml_to_json(v).map(|v| (k, v)))
                .collect::<Result<Map<_, _>, _>>()?,
        ),
    })
}

/// Reads a TOML or JSON file (by its extension) as a value tree.
pub fn read_tree(path: &Path) -> Result<Value, SettingsError> {
    let format = Format::of(path)?;
    let text = std::fs::read_to_string(path).map_err(|source| SettingsError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    // A leading byte-order mark (Windows editors) is not part of the document.
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    let syntax = |message: String| SettingsError::Syntax {
        path: path.to_path_buf(),
        message,
    };
    match format {
        Format::Json => serde_json::from_str(text).map_err(|e| syntax(e.to_string())),
        Format::Toml => {
            let table: toml::Table =
                toml::from_str(text).map_err(|e| syntax(e.to_string().trim().to_string()))?;
            toml_to_json(toml::Value::Table(table)).map_err(syntax)
        }
    }
}

/// `config` as a value tree (`None` is `null`).
pub fn to_tree<T: Serialize>(config: &T) -> Result<Value, SettingsError> {
    serde_json::to_value(config).map_err(|e| SettingsError::Serialize(e.to_string()))
}

/// Deep merge: the keys of `overlay` replace those of `base`, tables are merged key by key.
pub fn merge(base: &mut Value, overlay: Value) {
    match (base, overlay) {
        (Value::Object(b), Value::Object(o)) => {
            for (k, v) in o {
                match b.get_mut(&k) {
                    Some(slot) => merge(slot, v),
                    None => {
                        b.insert(k, v);
                    }
                }
            }
        }
        (slot, v) => *slot = v,
    }
}

/// Deserialises a value tree, naming the key of the first problem. `origin` says where the
/// values came from (for the error).
pub fn from_tree<T: DeserializeOwned>(tree: Value, origin: &str) -> Result<T, SettingsError> {
    serde_path_to_error::deserialize(tree).map_err(|e| {
        let path = e.path().to_string();
        let message = e.into_inner().to_string();
        describe(origin, &path, &message)
    })
}

/// Turns serde's message at `path` into an error naming the full key.
fn describe(origin: &str, path: &str, message: &str) -> SettingsError {
    let path = if path == "." { "" } else { path };
    if let Some(rest) = message.strip_prefix("unknown field `") {
        if let Some((field, tail)) = rest.split_once('`') {
            // serde_path_to_error's path already ends in the unknown key; older versions stop
            // at the enclosing struct.
            let key = if path == field || path.ends_with(&format!(".{field}")) {
                path.to_string()
            } else if path.is_empty() {
                field.to_string()
            } else {
                format!("{path}.{field}")
            };
            let expected = tail.trim_start_matches(',').trim();
            return SettingsError::UnknownKey {
                origin: origin.to_string(),
                key,
                expected: if expected.is_empty() {
                    String::new()
                } else {
                    format!("; {expected}")
                },
            };
        }
    }
    SettingsError::Invalid {
        origin: origin.to_string(),
        key: path.to_string(),
        message: message.to_string(),
    }
}

/// `base` with the keys of the file at `path` (TOML or JSON by extension) put over it.
pub fn load_file<T: Serialize + DeserializeOwned>(
    base: &T,
    path: &Path,
) -> Result<T, SettingsError> {
    let mut tree = to_tree(base)?;
    merge(&mut tree, read_tree(path)?);
    from_tree(tree, &path.display().to_string())
}

/// Sets `value` at `path` in `tree`; tables on the way are created when missing (an unknown
/// key is then reported by deserialisation, with its path).
fn set_path(tree: &mut Value, a: &Assignment) -> Result<(), SettingsError> {
    let mut node = tree;
    for (i, key) in a.path.iter().enumerate() {
        let last = i + 1 == a.path.len();
        let here = a.path[..=i].join(".");
        if node.is_null() && !last {
            *node = Value::Object(Map::new());
        }
        node = match node {
            Value::Object(m) => m
                .entry(key.clone())
                .or_insert_with(|| Value::Object(Map::new())),
            Value::Array(items) => {
                let len = items.len();
                let index: usize = key.parse().map_err(|_| SettingsError::Assignment {
                    assignment: a.text.clone(),
                    why: format!(
                        "`{}` is a list: index it with a number",
                        a.path[..i].join(".")
                    ),
                })?;
                items
                    .get_mut(index)
                    .ok_or_else(|| SettingsError::Assignment {
                        assignment: a.text.clone(),
                        why: format!("`{here}`: the list has {len} entries"),
                    })?
            }
            _ => {
                return Err(SettingsError::Assignment {
                    assignment: a.text.clone(),
                    why: format!("`{}` is a value, not a table", a.path[..i].join(".")),
                })
            }
        };
    }
    *node = a.value.clone();
    Ok(())
}

/// `base` with the assignments applied in order (each one checked by deserialisation, so an
/// error names the assignment that caused it).
pub fn apply_assignments<T: Serialize + DeserializeOwned>(
    base: &T,
    assignments: &[Assignment],
) -> Result<T, SettingsError> {
    let mut tree = to_tree(base)?;
    for a in assignments {
        set_path(&mut tree, a)?;
        // Checked one by one so that the error names the assignment at fault.
        from_tree::<T>(tree.clone(), &format!("--set {}", a.text))?;
    }
    from_tree(tree, "--set")
}

/// `base`, then the file at `file` (if any), then `assignments`.
pub fn load<T: Serialize + DeserializeOwned>(
    base: &T,
    file: Option<&Path>,
    assignments: &[Assignment],
) -> Result<T, SettingsError> {
    let config = match file {
        Some(p) => load_file(base, p)?,
        None => from_tree(to_tree(base)?, "defaults")?,
    };
    if assignments.is_empty() {
        Ok(config)
    } else {
        apply_assignments(&config, assignments)
    }
}

/// `config` as a TOML document (tables for nested structs; `None` values are left out).
pub fn to_toml<T: Serialize>(config: &T) -> Result<String, SettingsError> {
    toml::to_string_pretty(config).map_err(|e| SettingsError::Serialize(e.to_string()))
}

/// The rgbid version (`Cargo.toml`).
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// The git commit the library was built from, when it was built from a git checkout.
pub const GIT_COMMIT: Option<&str> = option_env!("RGBID_GIT_COMMIT");

/// What produced an output: recorded beside every result (`summary.json` of a run folder, or
/// a sidecar `<output>.json` next to a single output file).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Provenance {
    /// rgbid version.
    pub rgbid_version: String,
    /// Git commit of the build, when built from a git checkout.
    pub git_commit: Option<String>,
    /// Command line (program and arguments).
    pub command_line: Vec<String>,
    /// Compute backend: `cpu` or `gpu`.
    pub backend: String,
    /// GPU adapter name (with its graphics API), for the `gpu` backend.
    pub adapter: Option<String>,
    /// The configuration used, as a JSON object.
    pub config: Value,
}

impl Provenance {
    /// The provenance of a run of this process with `config` on `backend`.
    pub fn new<T: Serialize>(config: &T, backend: &ComputeBackend) -> Result<Self, SettingsError> {
        let (name, adapter) = match backend {
            ComputeBackend::Cpu => ("cpu", None),
            ComputeBackend::Gpu(g) => (
                "gpu",
                Some(format!("{} ({:?})", g.info.name, g.info.backend)),
            ),
        };
        Ok(Provenance {
            rgbid_version: VERSION.to_string(),
            git_commit: GIT_COMMIT.map(str::to_string),
            command_line: std::env::args().collect(),
            backend: name.to_string(),
            adapter,
            config: to_tree(config)?,
        })
    }

    /// The sidecar file of `output`: `output` with `.json` appended (`t.txt` -> `t.txt.json`).
    pub fn sidecar_path(output: &Path) -> PathBuf {
        let mut s = output.as_os_str().to_os_string();
        s.push(".json");
        PathBuf::from(s)
    }

    /// Writes the provenance as pretty JSON to the sidecar of `output`; returns its path.
    pub fn write_sidecar(&self, output: &Path) -> Result<PathBuf, SettingsError> {
        let path = Self::sidecar_path(output);
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| SettingsError::Serialize(e.to_string()))?;
        std::fs::write(&path, text + "\n").map_err(|source| SettingsError::Read {
            path: path.clone(),
            source,
        })?;
        Ok(path)
    }

    /// Writes the provenance and, under the key `summary`, what the run did (frames, frames
    /// skipped, status, warnings) as pretty JSON to the sidecar of `output`, replacing the file
    /// atomically (a run killed while writing leaves the previous sidecar); returns its path.
    pub fn write_sidecar_with_summary<S: Serialize>(
        &self,
        output: &Path,
        summary: &S,
    ) -> Result<PathBuf, SettingsError> {
        let path = Self::sidecar_path(output);
        let mut value =
            serde_json::to_value(self).map_err(|e| SettingsError::Serialize(e.to_string()))?;
        let summary =
            serde_json::to_value(summary).map_err(|e| SettingsError::Serialize(e.to_string()))?;
        if let Value::Object(map) = &mut value {
            map.insert("summary".into(), summary);
        }
        let text = serde_json::to_string_pretty(&value)
            .map_err(|e| SettingsError::Serialize(e.to_string()))?;
        super::write_atomic(&path, |w| {
            use std::io::Write;
            w.write_all(text.as_bytes())?;
            w.write_all(b"\n")
        })?;
        Ok(path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
    #[serde(default, deny_unknown_fields)]
    struct Inner {
        a: f64,
        list: Vec<usize>,
        maybe: Option<f64>,
    }

    impl Default for Inner {
        fn default() -> Self {
            Inner {
                a: 1.5,
                list: vec![1, 2, 3],
                maybe: Some(0.9),
            }
        }
    }

    #[derive(Clone, Debug, Default, PartialEq, Serialize, serde::Deserialize)]
    #[serde(default, deny_unknown_fields)]
    struct Outer {
        inner: Inner,
        name: String,
        flag: bool,
    }

    fn set(s: &str) -> Assignment {
        s.parse().expect("assignment")
    }

    #[test]
    fn assignments_parse_toml_values_and_fall_back_to_strings() {
        assert_eq!(set("a.b=3").value, Value::from(3));
        assert_eq!(set("a=0.5").value, Value::from(0.5));
        assert_eq!(set("a=true").value, Value::Bool(true));
        assert_eq!(set("a=huber").value, Value::from("huber"));
        assert_eq!(set("a=office:loop").value, Value::from("office:loop"));
        assert_eq!(set("a=[6, 8]").value, serde_json::json!([6, 8]));
        assert_eq!(set("a=null").value, Value::Null);
        assert_eq!(set("a.b=1").path, vec!["a", "b"]);
        assert!("novalue".parse::<Assignment>().is_err());
        assert!("a..b=1".parse::<Assignment>().is_err());
        assert!("a=inf".parse::<Assignment>().is_err());
    }

    #[test]
    fn assignments_apply_with_types_checked() {
        let c = apply_assignments(
            &Outer::default(),
            &[
                set("inner.a=2"),
                set("inner.list.1=7"),
                set("name=x"),
                set("inner.maybe=null"),
            ],
        )
        .expect("apply");
        assert_eq!(c.inner.a, 2.0);
        assert_eq!(c.inner.list, vec![1, 7, 3]);
        assert_eq!(c.name, "x");
        assert_eq!(c.inner.maybe, None);
        let e = apply_assignments(&Outer::default(), &[set("inner.aa=2")]).unwrap_err();
        assert!(
            matches!(&e, SettingsError::UnknownKey { key, .. } if key == "inner.aa"),
            "{e}"
        );
        let e = apply_assignments(&Outer::default(), &[set("nope.a=2")]).unwrap_err();
        assert!(
            matches!(&e, SettingsError::UnknownKey { key, .. } if key == "nope"),
            "{e}"
        );
        let e = apply_assignments(&Outer::default(), &[set("flag=maybe")]).unwrap_err();
        assert!(
            matches!(&e, SettingsError::Invalid { key, origin, .. } if key == "flag" && origin.contains("flag=maybe")),
            "{e}"
        );
        let e = apply_assignments(&Outer::default(), &[set("name.x=1")]).unwrap_err();
        assert!(matches!(e, SettingsError::Assignment { .. }), "{e}");
        let e = apply_assignments(&Outer::default(), &[set("inner.list.9=1")]).unwrap_err();
        assert!(matches!(e, SettingsError::Assignment { .. }), "{e}");
    }

    #[test]
    fn files_layer_over_the_base_and_name_unknown_keys() {
        let dir = tempfile::tempdir().expect("tempdir");
        let base = Outer {
            name: "base".into(),
            ..Default::default()
        };
        let toml_path = dir.path().join("c.toml");
        std::fs::write(&toml_path, "flag = true\n[inner]\na = 4.0\n").expect("write");
        let c = load_file(&base, &toml_path).expect("toml");
        assert_eq!((c.inner.a, c.flag, c.name.as_str()), (4.0, true, "base"));
        assert_eq!(c.inner.list, vec![1, 2, 3]);

        let json_path = dir.path().join("c.json");
        std::fs::write(&json_path, r#"{"inner": {"maybe": null}}"#).expect("write");
        let c = load_file(&base, &json_path).expect("json");
        assert_eq!(c.inner.maybe, None);

        std::fs::write(&toml_path, "[inner]\nb = 1\n").expect("write");
        let e = load_file(&base, &toml_path).unwrap_err();
        let text = e.to_string();
        assert!(
            text.contains("inner.b") && text.contains("c.toml"),
            "{text}"
        );

        std::fs::write(&toml_path, "[inner\n").expect("write");
        assert!(matches!(
            load_file(&base, &toml_path),
            Err(SettingsError::Syntax { .. })
        ));
        let other = dir.path().join("c.yaml");
        std::fs::write(&other, "a: 1").expect("write");
        assert!(matches!(
            load_file(&base, &other),
            Err(SettingsError::Format { .. })
        ));
        assert!(matches!(
            load_file(&base, &dir.path().join("missing.toml")),
            Err(SettingsError::Read { .. })
        ));
    }

    #[test]
    fn toml_round_trip() {
        let c = Outer::default();
        let text = to_toml(&c).expect("toml");
        let back: Outer = toml::from_str(&text).expect("parse");
        assert_eq!(back, c);
    }

    #[test]
    fn sidecar_appends_json() {
        assert_eq!(
            Provenance::sidecar_path(Path::new("out/t.txt")),
            PathBuf::from("out/t.txt.json")
        );
    }
}

//! The configuration as annotated TOML: every key with its one-line-or-more documentation as
//! comments, read from the doc comments of the structs that define the keys (so the listing
//! cannot drift from the code). `gausmoke-train config` prints it; runs write their
//! `config.toml` this way.

use crate::config::TrainConfig;

/// The sources whose `pub struct`s define the keys: the top level and its tables.
const SOURCES: [&str; 2] = [include_str!("config.rs"), include_str!("scene.rs")];

/// The body of `pub struct name` in [`SOURCES`] (up to its closing brace).
fn struct_body(name: &str) -> Option<&'static str> {
    SOURCES.iter().find_map(|source| {
        let body = &source[source.find(&format!("pub struct {name} {{"))?..];
        Some(&body[..body.find("\n}\n").unwrap_or(body.len())])
    })
}

/// The doc comment of field `key` of `pub struct name` in [`SOURCES`], one line per entry.
fn doc_of(name: &str, key: &str) -> Vec<String> {
    let mut doc = Vec::new();
    for line in struct_body(name).unwrap_or_default().lines() {
        let line = line.trim();
        if let Some(text) = line.strip_prefix("///") {
            doc.push(text.trim().to_string());
        } else if line.starts_with("#[") {
            continue;
        } else if line.starts_with(&format!("pub {key}:")) {
            return doc;
        } else {
            doc.clear();
        }
    }
    Vec::new()
}

/// The struct behind each table of the configuration.
fn struct_of(table: Option<&str>) -> &'static str {
    match table {
        None => "TrainConfig",
        Some("init_learning_rates") => "InitLearningRates",
        Some("scene") => "SceneConfig",
        Some(_) => "",
    }
}

fn comment(out: &mut String, doc: &[String]) {
    for line in doc {
        out.push_str(if line.is_empty() { "#" } else { "# " });
        out.push_str(line);
        out.push('\n');
    }
}

/// `config` as TOML with each key's documentation above it; a key left unset (an optional one)
/// is listed commented out.
pub fn annotated_toml(config: &TrainConfig) -> String {
    let table = toml::Table::try_from(config).expect("the configuration serialises to TOML");
    let mut out = String::new();
    let mut tables = Vec::new();
    for key in field_order(None) {
        match table.get(&key) {
            Some(toml::Value::Table(inner)) => tables.push((key, inner.clone())),
            Some(value) => {
                comment(&mut out, &doc_of(struct_of(None), &key));
                out.push_str(&format!("{key} = {value}\n\n"));
            }
            None => {
                comment(&mut out, &doc_of(struct_of(None), &key));
                out.push_str(&format!("# {key} = (unset)\n\n"));
            }
        }
    }
    for (name, inner) in tables {
        out.push_str(&format!("[{name}]\n"));
        for key in field_order(Some(&name)) {
            comment(&mut out, &doc_of(struct_of(Some(&name)), &key));
            match inner.get(&key) {
                Some(value) => out.push_str(&format!("{key} = {value}\n\n")),
                None => out.push_str(&format!("# {key} = (unset)\n\n")),
            }
        }
    }
    out.truncate(out.trim_end().len());
    out.push('\n');
    out
}

/// The fields of the struct behind `table`, in the order the source declares them.
fn field_order(table: Option<&str>) -> Vec<String> {
    struct_body(struct_of(table))
        .unwrap_or_default()
        .lines()
        .filter_map(|line| {
            let field = line.trim().strip_prefix("pub ")?;
            let (key, _) = field.split_once(':')?;
            key.chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
                .then(|| key.to_string())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preset::{Preset, Scale};

    /// Every key is documented, the listing reads back as the same configuration, and the
    /// unset scene keys are listed commented out.
    #[test]
    fn every_key_is_listed_with_its_documentation_and_reads_back() {
        let config = Preset::Ours.config(Scale::Quick);
        let text = annotated_toml(&config);
        let back: TrainConfig = toml::from_str(&text).unwrap();
        assert_eq!(back, config);
        let table = toml::Table::try_from(&config).unwrap();
        let mut keys: Vec<(Option<String>, String)> = Vec::new();
        for (key, value) in &table {
            match value {
                toml::Value::Table(inner) => {
                    keys.extend(inner.keys().map(|k| (Some(key.clone()), k.clone())))
                }
                _ => keys.push((None, key.clone())),
            }
        }
        keys.extend(
            ["open_faces", "open_face_flow", "inflow"].map(|k| (Some("scene".into()), k.into())),
        );
        let undocumented: Vec<String> = keys
            .iter()
            .filter(|(table, key)| doc_of(struct_of(table.as_deref()), key).is_empty())
            .map(|(table, key)| format!("{table:?}.{key}"))
            .collect();
        assert!(undocumented.is_empty(), "undocumented: {undocumented:?}");
        assert!(text.contains("# inflow = (unset)"), "{text}");
        assert!(text.contains("[scene]") && text.contains("[init_learning_rates]"));
    }
}

//! The configuration as annotated TOML: every key with its one-line-or-more documentation as
//! comments, read from the doc comments of the structs that define the keys (so the listing
//! cannot drift from the code). `gausmoke-train config` prints it; runs write their
//! `config.toml` this way.

use crate::config::TrainConfig;

/// The sources whose `pub struct`s define the keys: the top level and its tables.
const SOURCES: [&str; 3] = [
    include_str!("config.rs"),
    include_str!("config/tables.rs"),
    include_str!("scene.rs"),
];

/// The body of `pub struct name` in [`SOURCES`] (up to its closing brace).
fn struct_body(name: &str) -> Option<&'static str> {
    SOURCES.iter().find_map(|source| {
        let body = &source[source.find(&format!("pub struct {name} {{"))?..];
        Some(&body[..body.find("\n}\n").unwrap_or(body.len())])
    })
}

/// The fields of `pub struct name`, in the order the source declares them, each with its
/// type and its doc comment (one line per entry).
fn fields_of(name: &str) -> Vec<Field> {
    let mut fields = Vec::new();
    let mut doc = Vec::new();
    for line in struct_body(name).unwrap_or_default().lines().skip(1) {
        let line = line.trim();
        if let Some(text) = line.strip_prefix("///") {
            doc.push(text.trim().to_string());
        } else if line.starts_with("#[") {
            continue;
        } else if let Some((key, kind)) = line
            .strip_prefix("pub ")
            .and_then(|field| field.split_once(':'))
        {
            fields.push(Field {
                key: key.to_string(),
                kind: kind.trim().trim_end_matches(',').to_string(),
                doc: std::mem::take(&mut doc),
            });
        } else {
            doc.clear();
        }
    }
    fields
}

struct Field {
    key: String,
    /// The Rust type, as the source spells it.
    kind: String,
    doc: Vec<String>,
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
    write_table(&mut out, None, "TrainConfig", &table);
    out.truncate(out.trim_end().len());
    out.push('\n');
    out
}

/// The keys of `table` (the struct `name`'s values) under the header `[path]`, then its tables.
fn write_table(out: &mut String, path: Option<&str>, name: &str, table: &toml::Table) {
    let mut tables = Vec::new();
    for field in fields_of(name) {
        match table.get(&field.key) {
            Some(toml::Value::Table(inner)) => tables.push((field, inner)),
            Some(value) => {
                comment(out, &field.doc);
                out.push_str(&format!("{} = {value}\n\n", field.key));
            }
            None => {
                comment(out, &field.doc);
                out.push_str(&format!("# {} = (unset)\n\n", field.key));
            }
        }
    }
    for (field, inner) in tables {
        let path = match path {
            Some(path) => format!("{path}.{}", field.key),
            None => field.key.clone(),
        };
        comment(out, &field.doc);
        out.push_str(&format!("[{path}]\n"));
        write_table(out, Some(&path), &field.kind, inner);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preset::{Preset, Scale};

    /// The keys of `table` (nested ones dotted), each with the struct that documents it.
    fn keys(prefix: &str, name: &str, out: &mut Vec<(String, Vec<String>)>) {
        for field in fields_of(name) {
            let key = format!("{prefix}{}", field.key);
            if field.kind.ends_with("Config") || field.kind.ends_with("Rates") {
                keys(&format!("{key}."), &field.kind, out);
            } else {
                out.push((key, field.doc));
            }
        }
    }

    /// Every key is documented and listed, the listing reads back as the same configuration,
    /// unset keys are listed commented out, and there are at most about 60 keys.
    #[test]
    fn every_key_is_listed_with_its_documentation_and_reads_back() {
        let config = Preset::Ours.config(Scale::Quick);
        let text = annotated_toml(&config);
        let back: TrainConfig = toml::from_str(&text).unwrap();
        assert_eq!(back, config);
        let mut all = Vec::new();
        keys("", "TrainConfig", &mut all);
        let undocumented: Vec<&String> = all
            .iter()
            .filter(|(_, doc)| doc.is_empty())
            .map(|(key, _)| key)
            .collect();
        assert!(undocumented.is_empty(), "undocumented: {undocumented:?}");
        // Each key is in the listing, set or commented out, under its table.
        for (key, _) in &all {
            let (table, leaf) = key.rsplit_once('.').unwrap_or(("", key));
            let header = format!("[{table}]\n");
            let section = if table.is_empty() {
                &text[..text.find("\n[").unwrap_or(text.len())]
            } else {
                let start = text.find(&header).unwrap_or_else(|| panic!("no {header}"));
                let rest = &text[start + header.len()..];
                &rest[..rest.find("\n[").unwrap_or(rest.len())]
            };
            assert!(
                section.contains(&format!("\n{leaf} = "))
                    || section.contains(&format!("# {leaf} = ")),
                "{key} is not listed"
            );
        }
        assert!(all.len() <= 60, "{} keys", all.len());
        assert!(text.contains("# inflow = (unset)"), "{text}");
        assert!(text.contains("[joint.look_ahead]\n") && text.contains("[init.learning_rates]\n"));
    }
}

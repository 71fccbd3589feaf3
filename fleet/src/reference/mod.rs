//! The mission and experiment files' reference, made from the configuration types themselves:
//! their JSON Schema ([`schema`], what `fleet schema` prints for editors such as Taplo) and
//! the Markdown page a user reads ([`files_markdown`], `docs/reference/files.md`). Every key a
//! file can hold is a field of those types (`deny_unknown_fields` refuses any other), so the
//! page cannot miss one, and a test compares the page in the repository with what this module
//! makes of the types now.

mod protocol;
pub use protocol::{protocol_markdown, undocumented as undocumented_protocol};

use schemars::Schema;
use serde_json::{Map, Value};
use std::fmt::Write as _;

/// Which file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum File {
    Mission,
    Experiment,
}

/// The JSON Schema of a file (draft 2020-12, as schemars makes it).
pub fn schema(file: File) -> Schema {
    match file {
        File::Mission => schemars::schema_for!(fleet_mission::config::MissionConfig),
        File::Experiment => schemars::schema_for!(crate::experiment::paper::ExperimentConfig),
    }
}

/// Keys whose description is missing, as `file: [table] key` (every key must say what it is).
pub fn undocumented(file: File) -> Vec<String> {
    let mut out = vec![];
    let page = Page::of(file);
    for table in page.tables() {
        for (key, field) in table.fields {
            let elsewhere = page.set_elsewhere(&table.label, key).is_some();
            if !elsewhere && description(&page.resolve(field)).is_empty() && description(field).is_empty() {
                out.push(format!("{}: {} {key}", page.name, table.label));
            }
        }
    }
    out
}

/// The reference page of both files, in Markdown.
pub fn files_markdown() -> String {
    let mut md = String::from(
        "# The mission and experiment files\n\n\
         Made from the configuration types by `fleet reference files` (a test compares this page with \
         what the types say now: it cannot drift). Every key a file can hold is here, with its type, \
         its default (absent: required) and its meaning; a key that is not here is refused, naming it \
         (exit 2). `fleet schema mission` and `fleet schema experiment` print the same as JSON Schema, for \
         editors that complete and check TOML against one (Taplo: `#:schema ./mission.schema.json` on a \
         file's first line).\n\n",
    );
    for file in [File::Mission, File::Experiment] {
        Page::of(file).write(&mut md);
    }
    md
}

/// One file's schema and how its page is written.
struct Page {
    name: &'static str,
    readers: &'static str,
    root: Value,
}

/// A table of a file: its label (`top level`, `[team]`, `[[row]]`), its keys' schemas, the
/// keys it requires, and the schema of the keys it takes besides (`[sensors]`' vehicle ids).
struct Table<'a> {
    label: String,
    about: String,
    fields: Vec<(&'a String, &'a Value)>,
    required: Vec<String>,
    others: Option<Value>,
}

impl Page {
    fn of(file: File) -> Self {
        let root = schema(file).to_value();
        match file {
            File::Mission => Self {
                name: "mission",
                readers:
                    "Read by `fleet up`, `model-server`, `vehicle`, `gcs-gateway`, `fleet-watch`, `fleet secure`, \
                          `fleet replay` and `fleet assimilate` (every node of a mission reads the same file). The \
                          bundled `config/mission.toml` is the default; `config/mission-field.toml` is the template \
                          of a real site.",
                root,
            },
            File::Experiment => Self {
                name: "experiment",
                readers: "Read by `fleet experiment`. `config/experiment-paper.toml` (the paper's rows), \
                          `config/experiment-mission.toml` (the default mission as a row) and \
                          `config/experiment-real.toml` (real fields) are examples. Its `[team]` is the \
                          mission's `[team]`, less the keys each row sets (the rates, the noise, the radius, \
                          the placement and the seed).",
                root,
            },
        }
    }

    /// `$ref`s followed (`#/$defs/Name`), and a single `allOf` or `anyOf` with `null`
    /// (an `Option`) unwrapped, to the schema that says what a value is.
    fn resolve<'a>(&'a self, v: &'a Value) -> std::borrow::Cow<'a, Value> {
        if let Some(r) = v.get("$ref").and_then(Value::as_str) {
            let name = r.trim_start_matches("#/$defs/");
            if let Some(def) = self.root.get("$defs").and_then(|d| d.get(name)) {
                return self.resolve(def);
            }
        }
        for key in ["anyOf", "oneOf"] {
            if let Some(list) = v.get(key).and_then(Value::as_array) {
                let not_null: Vec<&Value> = list.iter().filter(|s| s.get("type") != Some(&"null".into())).collect();
                if not_null.len() == 1 && not_null.len() < list.len() {
                    return self.resolve(not_null[0]);
                }
            }
        }
        std::borrow::Cow::Borrowed(v)
    }

    /// Whether a key's value is a table of its own (an object with named keys).
    fn is_table(&self, v: &Value) -> bool {
        let v = self.resolve(v);
        v.get("properties")
            .is_some_and(|p| p.as_object().is_some_and(|o| !o.is_empty()))
    }

    /// The top level, then each key that is a table (`[name]`) or an array of tables (`[[name]]`).
    fn tables(&self) -> Vec<Table<'_>> {
        let props = properties(&self.root);
        let top: Vec<_> = props
            .iter()
            .filter(|(_, v)| !self.is_table(v) && !self.is_table_array(v))
            .map(|(k, v)| (*k, *v))
            .collect();
        let mut tables = vec![Table {
            label: "top level".into(),
            about: String::new(),
            fields: top,
            required: required(&self.root),
            others: None,
        }];
        for (key, v) in props {
            let (label, inner) = match (self.is_table(v), self.is_table_array(v)) {
                (true, _) => (format!("[{key}]"), self.resolve(v).into_owned()),
                (_, true) => (
                    format!("[[{key}]]"),
                    self.resolve(&self.resolve(v)["items"]).into_owned(),
                ),
                _ => continue,
            };
            let about = [description(v), description(&inner)]
                .into_iter()
                .find(|d| !d.is_empty())
                .unwrap_or_default();
            let fields = self.fields_of(&inner);
            let others = inner.get("additionalProperties").filter(|a| a.is_object()).cloned();
            tables.push(Table {
                label,
                about,
                fields,
                required: required(&inner),
                others,
            });
        }
        tables
    }

    fn is_table_array(&self, v: &Value) -> bool {
        let v = self.resolve(v);
        v.get("type") == Some(&"array".into()) && v.get("items").is_some_and(|i| self.is_table(i))
    }

    /// The keys of a table's schema, found again in the root (so they borrow from `self`).
    fn fields_of(&self, inner: &Value) -> Vec<(&String, &Value)> {
        let title = inner.get("title").and_then(Value::as_str);
        let defs = self.root.get("$defs").and_then(Value::as_object);
        let found = defs.and_then(|d| {
            d.values()
                .find(|def| def.get("title").and_then(Value::as_str) == title && title.is_some())
                .or_else(|| d.values().find(|def| properties(def) == properties(inner)))
        });
        found.map(properties).unwrap_or_default()
    }

    fn write(&self, md: &mut String) {
        let _ = writeln!(md, "## The {} file\n\n{}\n", self.name, self.readers);
        for table in self.tables() {
            let _ = writeln!(md, "### {} ({} file)\n", table.label, self.name);
            if !table.about.is_empty() {
                let _ = writeln!(md, "{}\n", table.about);
            }
            let _ = writeln!(md, "| key | type | default | meaning |\n|---|---|---|---|");
            for (key, field) in &table.fields {
                let resolved = self.resolve(field);
                let mut meaning = [description(field), description(&resolved)]
                    .into_iter()
                    .find(|d| !d.is_empty())
                    .unwrap_or_default();
                if let Some(elsewhere) = self.set_elsewhere(&table.label, key) {
                    meaning = format!("Not here: an experiment sets it by {elsewhere}.");
                }
                let default = match field.get("default") {
                    Some(d) => format!("`{}`", compact(d)),
                    None if table.required.contains(key) => "required".into(),
                    None => "none".into(),
                };
                let _ = writeln!(
                    md,
                    "| `{key}` | {} | {default} | {} |",
                    self.type_of(field),
                    cell(&meaning)
                );
            }
            // The one table with keys of the user's naming (`[sensors]`: a vehicle's id).
            if let Some(others) = &table.others {
                let _ = writeln!(
                    md,
                    "| *a vehicle's id* | {} | the `default` | That vehicle's source, in `default`'s forms. |",
                    self.type_of(others),
                );
            }
            md.push('\n');
        }
    }

    /// Where an experiment sets a `[team]` key it refuses in its `[team]`.
    fn set_elsewhere(&self, label: &str, key: &str) -> Option<&'static str> {
        if self.name != "experiment" || label != "[team]" {
            return None;
        }
        crate::experiment::paper::SET_ELSEWHERE
            .iter()
            .find(|(k, _)| *k == key)
            .map(|(_, by)| *by)
    }

    /// A value's type in words: `integer`, `string`, one of its values, an array of them.
    fn type_of(&self, v: &Value) -> String {
        let r = self.resolve(v);
        if let Some(values) = r.get("enum").and_then(Value::as_array) {
            return format!(
                "one of {}",
                values
                    .iter()
                    .map(|e| format!("`{}`", compact(e)))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        if let Some(list) = r.get("oneOf").or(r.get("anyOf")).and_then(Value::as_array) {
            let kinds: Vec<String> = list.iter().map(|s| self.type_of(s)).collect();
            return kinds.join(" or ");
        }
        if let Some(c) = r.get("const") {
            return format!("`{}`", compact(c));
        }
        match r.get("type") {
            Some(Value::String(t)) if t == "array" => match r.get("items") {
                Some(items) => format!("array of {}", self.type_of(items)),
                None => "array".into(),
            },
            Some(Value::String(t)) if t == "object" => match r.get("additionalProperties") {
                Some(Value::Object(_)) => format!("table of {}", self.type_of(&r["additionalProperties"])),
                _ => "table".into(),
            },
            Some(Value::String(t)) => t.clone(),
            Some(Value::Array(ts)) => {
                let kinds: Vec<&Value> = ts.iter().filter(|t| *t != "null").collect();
                match kinds.as_slice() {
                    [one] => {
                        let mut single = r.as_ref().clone();
                        single["type"] = (*one).clone();
                        self.type_of(&single)
                    }
                    _ => kinds
                        .iter()
                        .map(|t| t.as_str().unwrap_or("?"))
                        .collect::<Vec<_>>()
                        .join(" or "),
                }
            }
            _ => "any".into(),
        }
    }
}

fn properties(v: &Value) -> Vec<(&String, &Value)> {
    v.get("properties")
        .and_then(Value::as_object)
        .map(|o: &Map<String, Value>| o.iter().collect())
        .unwrap_or_default()
}

fn required(v: &Value) -> Vec<String> {
    v.get("required")
        .and_then(Value::as_array)
        .map(|r| r.iter().filter_map(|s| s.as_str().map(String::from)).collect())
        .unwrap_or_default()
}

/// A description on one line (the doc comment's lines joined), its rustdoc links as plain code
/// (`` [`crate::health`] `` is `` `crate::health` `` to a reader of the page).
fn description(v: &Value) -> String {
    let text = v
        .get("description")
        .and_then(Value::as_str)
        .map(|d| d.split_whitespace().collect::<Vec<_>>().join(" "))
        .unwrap_or_default();
    let mut out = String::with_capacity(text.len());
    let mut rest = text.as_str();
    while let Some(at) = rest.find("[`") {
        let Some(end) = rest[at..].find("`]") else { break };
        out.push_str(&rest[..at]);
        out.push_str(&rest[at + 1..at + end + 1]);
        rest = &rest[at + end + 2..];
    }
    out.push_str(rest);
    out
}

/// A table cell: a `|` escaped.
fn cell(text: &str) -> String {
    text.replace('|', "\\|")
}

/// A JSON value as TOML would mostly show it, on one line.
fn compact(v: &Value) -> String {
    match v {
        Value::String(s) => format!("\"{s}\""),
        Value::Null => "none".into(),
        other => other.to_string(),
    }
}

/// That `docs/reference/<page>` is `made`, what `fleet reference <command>` prints.
#[cfg(test)]
fn assert_page_is(page: &str, made: &str, command: &str) {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../docs/reference")
        .join(page);
    let committed = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        committed == made,
        "{} is not what the types say: make it again with `fleet reference {command} > docs/reference/{page}`",
        path.display()
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every key of both files says what it is (a key without a doc comment has an empty
    /// meaning on the page).
    #[test]
    fn every_key_says_what_it_is() {
        let missing: Vec<String> = [File::Mission, File::Experiment]
            .into_iter()
            .flat_map(undocumented)
            .collect();
        assert!(
            missing.is_empty(),
            "keys without a description:\n{}",
            missing.join("\n")
        );
    }

    /// The page in the repository is what the types say now: a key added, removed, renamed or
    /// redocumented without the page made again fails here.
    #[test]
    fn the_files_reference_is_the_types() {
        assert_page_is("files.md", &files_markdown(), "files");
    }
}

//! The wire protocol's reference page (`docs/reference/protocol.md`), made from the protocol
//! itself: the keys from [`Keys`] and their catalogue, the encoding and the schema version from
//! their constants, and every message's fields from the message types' JSON Schema (their doc
//! comments and serde's names, defaults and tags), so that a field added, renamed or
//! redocumented shows on the page, and a test fails until the page is made again. What the
//! types cannot say (how packed arrays and cell runs are read, an observer in Python) is the
//! prose of `protocol-notes.md`, beside this file.

use super::{description, properties, required};
use fleet_mission::protocol::{keys::Keys, Body, ENCODING, SCHEMA_VERSION};
use schemars::generate::SchemaSettings;
use serde_json::{Map, Value};
use std::fmt::Write as _;

/// How the packed arrays and cell runs are read, and an observer in Python.
const NOTES: &str = include_str!("protocol-notes.md");

/// The page, in Markdown.
pub fn protocol_markdown() -> String {
    let mut md = format!(
        "# The wire protocol\n\n\
         Made from the protocol's types by `fleet reference protocol` (a test compares this page with what \
         the types say now: it cannot drift). Every payload is one CBOR map, Zenoh encoding `{ENCODING}`: \
         `{{\"v\": {SCHEMA_VERSION}, \"type\": ..., ...fields}}`, the schema version and the message's type \
         beside its fields. A node refuses a message of another version, and counts it.\n\n"
    );
    write_keys(&mut md);
    let schema = MessageSchema::new();
    schema.write(&mut md);
    md.push_str(NOTES);
    md
}

/// Fields (of messages and of the types inside them) that do not say what they are.
pub fn undocumented() -> Vec<String> {
    let schema = MessageSchema::new();
    let mut out = vec![];
    for (name, def) in &schema.defs {
        for (field, v) in properties(def) {
            if description(v).is_empty() {
                out.push(format!("{name}.{field}"));
            }
        }
    }
    out
}

/// The keys of a mission `<mission>`, each with what travels on it and who puts and reads it.
fn write_keys(md: &mut String) {
    md.push_str(
        "## Keys\n\n\
         Every key lives under `fleet/<mission>/`; ids (the mission's, a vehicle's) are 1-32 characters of \
         `A-Za-z0-9_-`.\n\n\
         | key | what travels | put by | read by |\n|---|---|---|---|\n",
    );
    let keys = Keys::new("m").expect("a valid mission id");
    for k in keys.catalogue("<id>") {
        let leaf = k.key.strip_prefix("fleet/m/").unwrap_or(&k.key);
        let _ = writeln!(md, "| `{leaf}` | {} | {} | {} |", k.payload, k.put_by, k.read_by);
    }
    md.push('\n');
}

/// The messages' JSON Schema: each `type` tag with its type's name, and every type's schema.
struct MessageSchema {
    /// `(tag, type name)` in the order of [`Body`]'s variants.
    messages: Vec<(String, String)>,
    defs: Map<String, Value>,
}

impl MessageSchema {
    fn new() -> Self {
        let generator = SchemaSettings::draft2020_12().into_generator();
        let root = generator.into_root_schema_for::<Body>().to_value();
        let defs = root
            .get("$defs")
            .and_then(Value::as_object)
            .cloned()
            .unwrap_or_default();
        let variants = root.get("oneOf").and_then(Value::as_array).cloned().unwrap_or_default();
        let messages = variants.iter().filter_map(tag_and_type).collect();
        Self { messages, defs }
    }

    fn write(&self, md: &mut String) {
        md.push_str(
            "## Messages\n\n\
             A field whose default is given may be absent (it is then that value); the others are always \
             there. Integers are unsigned unless said; numbers are 64-bit floats.\n\n",
        );
        for (tag, name) in &self.messages {
            let _ = writeln!(md, "### `{tag}`: {name}\n");
            self.write_fields(md, name);
        }
        md.push_str("## Types inside messages\n\n");
        let shown: Vec<&String> = self.messages.iter().map(|(_, n)| n).collect();
        for name in self.defs.keys().filter(|n| !shown.contains(n)) {
            let _ = writeln!(md, "### {name}\n");
            self.write_fields(md, name);
        }
    }

    /// A type's doc and its table of fields (or its values, for an enum of names).
    fn write_fields(&self, md: &mut String, name: &str) {
        let def = &self.defs[name];
        let about = description(def);
        if !about.is_empty() {
            let _ = writeln!(md, "{about}\n");
        }
        if let Some(values) = names_of(def) {
            let _ = writeln!(md, "One of {}.\n", values.join(", "));
            return;
        }
        let required = required(def);
        md.push_str("| field | type | default | meaning |\n|---|---|---|---|\n");
        for (field, v) in properties(def) {
            let default = match v.get("default") {
                Some(Value::Null) => "absent".into(),
                Some(d) => format!("`{d}`"),
                None if required.contains(field) => "required".into(),
                None => "absent".into(),
            };
            let meaning = description(v).replace('|', "\\|");
            let _ = writeln!(md, "| `{field}` | {} | {default} | {meaning} |", self.type_of(v));
        }
        md.push('\n');
    }

    /// A value's type in words, a type of its own as a link to its section.
    fn type_of(&self, v: &Value) -> String {
        if let Some(wire) = v.get("x-wire").and_then(Value::as_str) {
            return wire.to_string();
        }
        if let Some(name) = v
            .get("$ref")
            .and_then(Value::as_str)
            .map(|r| r.trim_start_matches("#/$defs/"))
        {
            return match self.defs.get(name).and_then(names_of) {
                Some(values) => format!("one of {}", values.join(", ")),
                None => format!("[{name}](#{})", name.to_lowercase()),
            };
        }
        if let Some(list) = v.get("anyOf").or(v.get("oneOf")).and_then(Value::as_array) {
            let kinds: Vec<String> = list.iter().filter(|s| !is_null(s)).map(|s| self.type_of(s)).collect();
            return kinds.join(" or ");
        }
        let kind = match v.get("type") {
            Some(Value::Array(ts)) => ts.iter().find(|t| *t != "null").and_then(Value::as_str),
            Some(t) => t.as_str(),
            None => None,
        };
        match kind {
            Some("array") => match (v.get("items"), v.get("minItems"), v.get("maxItems")) {
                (Some(items), Some(lo), Some(hi)) if lo == hi => format!("{lo} of {}", self.type_of(items)),
                (Some(items), _, _) => format!("array of {}", self.type_of(items)),
                _ => "array".into(),
            },
            Some("object") => match (v.get("additionalProperties"), v.get("patternProperties")) {
                (Some(inner @ Value::Object(_)), _) => format!("map of string to {}", self.type_of(inner)),
                (_, Some(Value::Object(keyed))) if keyed.len() == 1 => {
                    let (pattern, inner) = keyed.iter().next().expect("one key");
                    let key = match pattern == &vehicle_id_pattern() {
                        true => "vehicle id".to_string(),
                        false => format!("string matching `{pattern}`"),
                    };
                    format!("map of {key} to {}", self.type_of(inner))
                }
                _ => "map".into(),
            },
            Some("string") if v.get("pattern").and_then(Value::as_str) == Some(&vehicle_id_pattern()) => {
                "vehicle id (string)".into()
            }
            Some("integer") => match v.get("format").and_then(Value::as_str) {
                Some(f) => format!("integer ({f})"),
                None => "integer".into(),
            },
            Some(t) => t.to_string(),
            None => "any".into(),
        }
    }
}

/// How a vehicle id is written (1-32 characters of `A-Za-z0-9_-`), as its schema says it.
fn vehicle_id_pattern() -> String {
    let schema = schemars::SchemaGenerator::default().subschema_for::<fleet_mission::protocol::VehicleId>();
    schema
        .get("pattern")
        .and_then(Value::as_str)
        .unwrap_or_default()
        .to_string()
}

/// A variant of [`Body`]'s schema as its `type` tag and the name of its type.
fn tag_and_type(variant: &Value) -> Option<(String, String)> {
    let tag = variant.pointer("/properties/type/const")?.as_str()?.to_string();
    let reference = variant
        .get("$ref")
        .or_else(|| variant.get("allOf")?.as_array()?.iter().find_map(|s| s.get("$ref")))?;
    let name = reference.as_str()?.trim_start_matches("#/$defs/").to_string();
    Some((tag, name))
}

/// An enum of names (`"up"`, `"down"`) as its names in backticks.
fn names_of(def: &Value) -> Option<Vec<String>> {
    if let Some(values) = def.get("enum").and_then(Value::as_array) {
        return Some(
            values
                .iter()
                .map(|v| format!("`{}`", v.as_str().unwrap_or("?")))
                .collect(),
        );
    }
    let list = def.get("oneOf")?.as_array()?;
    list.iter()
        .map(|s| {
            let c = s.get("const").or_else(|| s.get("enum")?.as_array()?.first())?;
            Some(format!("`{}`", c.as_str()?))
        })
        .collect()
}

fn is_null(v: &Value) -> bool {
    v.get("type") == Some(&Value::String("null".into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every field of every message, and of every type inside one, says what it is.
    #[test]
    fn every_field_says_what_it_is() {
        let missing = undocumented();
        assert!(
            missing.is_empty(),
            "fields without a description:\n{}",
            missing.join("\n")
        );
    }

    /// The page in the repository is what the types say now.
    #[test]
    fn the_protocol_reference_is_the_types() {
        super::super::assert_page_is("protocol.md", &protocol_markdown(), "protocol");
    }

    /// Every message of [`Body`] is on the page under its tag, and a type is linked to its section.
    #[test]
    fn every_message_is_listed_under_its_tag() {
        let schema = MessageSchema::new();
        let tags: Vec<&str> = schema.messages.iter().map(|(t, _)| t.as_str()).collect();
        assert_eq!(
            tags,
            ["batch", "telemetry", "ack", "model", "plan", "status", "override"]
        );
        let md = protocol_markdown();
        assert!(md.contains("### `batch`: MeasurementBatch"), "{md}");
        assert!(md.contains("| `samples` | array of [Sample](#sample) |"), "{md}");
        assert!(md.contains("### Sample"), "{md}");
    }
}

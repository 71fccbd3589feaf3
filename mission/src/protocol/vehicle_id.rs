//! A vehicle's id, the one type every message and API names a vehicle by.

use super::{keys, ProtocolError};
use serde::{Deserialize, Serialize};

/// A vehicle id from outside (a command line, a message): 1-32 characters of `A-Z a-z 0-9 _ -`,
/// so it is safe inside a key expression and a file name.
/// Validated once, where it comes in (a message is refused when one of its ids is not one);
/// on the wire it is the string.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct VehicleId(String);

impl VehicleId {
    /// How the error of an id that is not one begins (`keys::check_id`'s message).
    pub const REFUSED: &'static str = "vehicle id ";

    pub fn new(id: &str) -> Result<Self, ProtocolError> {
        keys::check_id("vehicle", id)?;
        Ok(Self(id.to_string()))
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

/// On the wire a string, of the characters and length [`keys::check_id`] takes.
impl schemars::JsonSchema for VehicleId {
    fn inline_schema() -> bool {
        true
    }
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "VehicleId".into()
    }
    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        let pattern = format!("^[A-Za-z0-9_-]{{1,{}}}$", keys::MAX_ID_LEN);
        schemars::json_schema!({ "type": "string", "pattern": pattern })
    }
}

impl TryFrom<String> for VehicleId {
    /// What is wrong with it, beginning [`VehicleId::REFUSED`] (serde carries it as text).
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        match keys::check_id("vehicle", &s) {
            Ok(()) => Ok(Self(s)),
            Err(ProtocolError::Invalid(why)) => Err(why),
            Err(e) => Err(e.to_string()),
        }
    }
}

impl From<VehicleId> for String {
    fn from(id: VehicleId) -> String {
        id.0
    }
}

impl std::borrow::Borrow<str> for VehicleId {
    fn borrow(&self) -> &str {
        &self.0
    }
}

impl PartialEq<str> for VehicleId {
    fn eq(&self, other: &str) -> bool {
        self.0 == other
    }
}

impl PartialEq<&str> for VehicleId {
    fn eq(&self, other: &&str) -> bool {
        self.0 == *other
    }
}

impl PartialEq<VehicleId> for &str {
    fn eq(&self, other: &VehicleId) -> bool {
        *self == other.0
    }
}

impl PartialEq<VehicleId> for str {
    fn eq(&self, other: &VehicleId) -> bool {
        self == other.0
    }
}

impl PartialEq<String> for VehicleId {
    fn eq(&self, other: &String) -> bool {
        &self.0 == other
    }
}

impl PartialEq<VehicleId> for String {
    fn eq(&self, other: &VehicleId) -> bool {
        *self == other.0
    }
}

impl std::str::FromStr for VehicleId {
    type Err = ProtocolError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::new(s)
    }
}

impl std::ops::Deref for VehicleId {
    type Target = str;
    fn deref(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for VehicleId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

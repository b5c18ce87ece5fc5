//! Settings files in Pulicast 2.x's `puliconf` format, so files move
//! between `puli config` and `puliconf`: TOML, one key per setting (its
//! fleet-wide name; a leading `/` is allowed), `nan` for an unset value,
//! integers, floats, booleans and strings for values, and a table for a
//! native setting's structured value. A file keeps its order and comments
//! as read.

use std::fmt;
use std::str::FromStr;

use toml_edit::{DocumentMut, Item, Value};

use crate::catalog::SettingInfo;
use crate::setting::{item_value, json_to_toml, setting_key, FileValue};
use crate::wire::zcm::Primitive;

/// A settings file: what `puli config pull` writes and `push` and `diff`
/// read.
#[derive(Debug, Clone, Default)]
pub struct SettingsFile {
    doc: DocumentMut,
}

/// One key of a [`SettingsFile`].
#[derive(Debug, Clone, PartialEq)]
pub struct SettingsFileEntry {
    /// The setting's fleet-wide name (the key, without a leading `/`).
    pub name: String,
    /// Its value, or why the entry is not one a setting can take (a 2.x
    /// structured message, a date, an array of tables).
    pub value: Result<FileValue, String>,
}

/// A setting left out of a file, or an entry of a file not used, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SkippedSetting {
    /// The setting's fleet-wide name.
    pub name: String,
    /// Why, for a person to read.
    pub reason: String,
}

impl SkippedSetting {
    fn new(name: impl Into<String>, reason: impl Into<String>) -> Self {
        Self {
            name: name.into(),
            reason: reason.into(),
        }
    }
}

impl SettingsFile {
    /// An empty file.
    pub fn new() -> Self {
        Self::default()
    }

    /// The fleet's settings as a file, as `puliconf` pulls them: locked,
    /// stale and unconfirmed ones are left out (and returned with why),
    /// and each value is commented with what its owner says it is.
    pub fn pull(settings: &[SettingInfo]) -> (Self, Vec<SkippedSetting>) {
        let mut file = Self::new();
        let mut left_out = Vec::new();
        for s in settings {
            let why = if s.is_locked() {
                Some("locked: more than one node owns it")
            } else if s.is_stale() {
                Some("its owner is gone")
            } else {
                None
            };
            if let Some(why) = why {
                left_out.push(SkippedSetting::new(&s.name, why));
                continue;
            }
            let Some(mut value) = toml_of(s) else {
                left_out.push(SkippedSetting::new(
                    &s.name,
                    "its value is not one TOML holds",
                ));
                continue;
            };
            if let Some(about) = s.about.as_deref().filter(|a| !a.is_empty()) {
                // A comment is one line.
                let about = about.replace(['\n', '\r'], " ");
                value = value.decorated(" ", format!(" # {about}"));
            }
            file.doc.insert(&s.name, Item::Value(value));
        }
        (file, left_out)
    }

    /// The file's entries, in its order.
    pub fn entries(&self) -> Vec<SettingsFileEntry> {
        self.doc
            .iter()
            .map(|(key, item)| SettingsFileEntry {
                name: setting_key(key),
                value: item_value(item),
            })
            .collect()
    }

    /// The part of this file that differs from the fleet (`known`): what
    /// pushing it would change, as a file. Entries whose setting no node
    /// owns, and entries that are no value, are returned with why.
    pub fn differing(&self, known: &[SettingInfo]) -> (Self, Vec<SkippedSetting>) {
        let mut out = Self::new();
        let mut skipped = Vec::new();
        for (key, item) in self.doc.iter() {
            let name = setting_key(key);
            let Some(setting) = known.iter().find(|s| s.name == name) else {
                skipped.push(SkippedSetting::new(name, "no node owns this setting"));
                continue;
            };
            match item_value(item) {
                Ok(target) if setting.holds(&target) => {}
                Ok(_) => {
                    out.doc.insert(key, item.clone());
                }
                Err(why) => skipped.push(SkippedSetting::new(name, why)),
            }
        }
        (out, skipped)
    }

    /// How many keys the file has.
    pub fn len(&self) -> usize {
        self.doc.len()
    }

    /// Whether the file has no keys.
    pub fn is_empty(&self) -> bool {
        self.doc.is_empty()
    }
}

impl FromStr for SettingsFile {
    type Err = String;

    /// Reads a file's text; fails only on text that is not TOML (entries
    /// that are no value are reported by [`SettingsFile::entries`]).
    fn from_str(text: &str) -> Result<Self, String> {
        let doc = text.parse().map_err(|e| format!("not TOML: {e}"))?;
        Ok(Self { doc })
    }
}

impl fmt::Display for SettingsFile {
    /// The file's text.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Display::fmt(&self.doc, f)
    }
}

/// The TOML value of a setting's confirmed value, `None` if it has none
/// that TOML holds (not confirmed, or a structured message without JSON).
fn toml_of(setting: &SettingInfo) -> Option<Value> {
    let confirmed = setting.confirmed.as_ref()?;
    if !confirmed.is_set() {
        return Some(f64::NAN.into());
    }
    let Some(value) = confirmed.value.as_ref() else {
        // A native value, from its announced type.
        return json_to_toml(&setting.value_json()?);
    };
    Some(match value {
        Primitive::Bool(v) => (*v).into(),
        Primitive::Byte(v) => i64::from(*v).into(),
        Primitive::I8(v) => i64::from(*v).into(),
        Primitive::I16(v) => i64::from(*v).into(),
        Primitive::I32(v) => i64::from(*v).into(),
        Primitive::I64(v) => (*v).into(),
        Primitive::Float(v) | Primitive::Double(v) => (*v).into(),
        Primitive::String(v) => v.as_str().into(),
    })
}

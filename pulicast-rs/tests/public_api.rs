//! The public surface is a promise: its listing is checked in, and any
//! change to it shows up here as a failing diff until the listing (and the
//! account of it in `docs/architecture.md`) changes with it.
//!
//! The listing comes from rustdoc's JSON output (unstable, so it is read
//! on the stable toolchain with `RUSTC_BOOTSTRAP=1`), and names every
//! public path of `pulicast` and of the core crate `pulicast-proto`: items,
//! their public fields, variants, inherent methods and constants, and the
//! traits they implement. A `pub mod` that comes back (`pulicast::wire`)
//! adds its whole content to the listing, so this test catches it.
//!
//! Each line carries the item's signature too, not only its name, so a
//! changed type fails here as a removed name does: functions and methods
//! their generics, parameter types (names are no promise) and return type,
//! with the bounds of the impl they are in where it has any; fields their
//! type; constants and statics their type; type aliases their target;
//! generic types their parameters; traits their supertraits; trait items
//! their signature or bounds. Types are shown by the path a user names them
//! by: the item's public path in the listed crate where it has one, else
//! where it is defined; the standard library's by `std::` and their name
//! alone (`std::SocketAddr`), as its modules move between releases.
//!
//! Run with `PULICAST_BLESS=1` to write the listings after a deliberate
//! change.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::process::Command;

use serde_json::Value;

/// The crates whose public items a listing follows into, by rustdoc's
/// crate name.
const DOCUMENTED: [(&str, &str); 3] = [
    ("pulicast", "pulicast"),
    ("pulicast_proto", "pulicast-proto"),
    ("pulicast_discovery", "pulicast-discovery"),
];

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the crate sits in the workspace")
        .to_path_buf()
}

/// rustdoc's JSON for each documented crate, built into a target
/// directory of its own (the test's own build holds the usual one).
fn rustdoc_json() -> HashMap<&'static str, Value> {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join("target"))
        .join("public-api");
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut docs = HashMap::new();
    for (name, package) in DOCUMENTED {
        let out = Command::new(&cargo)
            .current_dir(workspace())
            .env("RUSTC_BOOTSTRAP", "1")
            .env("CARGO_TARGET_DIR", &target)
            .env_remove("RUSTDOCFLAGS")
            .args([
                "rustdoc", "--quiet", "--locked", "-p", package, "--lib", "--",
            ])
            .args(["-Z", "unstable-options", "--output-format", "json"])
            .output()
            .expect("cargo runs");
        assert!(
            out.status.success(),
            "rustdoc JSON of {package} failed:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let path = target.join("doc").join(format!("{name}.json"));
        let text = std::fs::read_to_string(&path).expect("rustdoc wrote its JSON");
        docs.insert(
            name,
            serde_json::from_str(&text).expect("rustdoc's JSON parses"),
        );
    }
    docs
}

/// Walks one crate's public surface into lines `path (kind) signature`.
struct Lister<'a> {
    docs: &'a HashMap<&'static str, Value>,
    lines: BTreeSet<String>,
    /// The public path of each item listed, by where it is defined
    /// (`pulicast_proto::view::MemberView` -> `pulicast::MemberView`):
    /// what a first walk found, for the second to name types by.
    names: HashMap<String, String>,
    /// What this walk finds, the same way.
    found: HashMap<String, String>,
}

impl<'a> Lister<'a> {
    fn item(&self, krate: &str, id: &Value) -> Option<&'a Value> {
        let key = match id {
            Value::Number(n) => n.to_string(),
            Value::String(s) => s.clone(),
            _ => return None,
        };
        self.docs[krate]["index"].get(&key)
    }

    /// Where a foreign item referred to from `krate` is defined: its crate
    /// (if documented here) and its item there.
    fn foreign(&self, krate: &str, id: &Value) -> Option<(&'static str, &'a Value)> {
        let doc = &self.docs[krate];
        let key = id.to_string().trim_matches('"').to_owned();
        let entry = doc["paths"].get(&key)?;
        let crate_id = entry["crate_id"].to_string();
        let crate_name = doc["external_crates"][&crate_id]["name"].as_str()?;
        let (home, _) = DOCUMENTED.iter().find(|(n, _)| *n == crate_name)?;
        let path: Vec<&str> = entry["path"]
            .as_array()?
            .iter()
            .filter_map(Value::as_str)
            .collect();
        let there = &self.docs[home];
        let (found, _) = there["paths"].as_object()?.iter().find(|(_, p)| {
            p["crate_id"] == 0
                && p["path"]
                    .as_array()
                    .is_some_and(|q| q.iter().filter_map(Value::as_str).eq(path.iter().copied()))
        })?;
        Some((home, there["index"].get(found)?))
    }

    fn add(&mut self, path: &str, what: &str) {
        self.lines.insert(format!("{path} ({what})"));
    }

    /// A line with its signature, if it has one.
    fn add_sig(&mut self, path: &str, what: &str, sig: &str) {
        if sig.is_empty() {
            self.add(path, what);
        } else {
            self.lines.insert(format!("{path} ({what}) {sig}"));
        }
    }

    /// Where the item `id` of `krate`'s JSON is defined
    /// (`pulicast_proto::view::MemberView`), if rustdoc says.
    fn defined_at(&self, krate: &str, id: &Value) -> Option<String> {
        let key = match id {
            Value::Number(n) => n.to_string(),
            Value::String(s) => s.clone(),
            _ => return None,
        };
        let path = self.docs[krate]["paths"].get(&key)?["path"].as_array()?;
        let path: Vec<&str> = path.iter().filter_map(Value::as_str).collect();
        Some(path.join("::"))
    }

    /// Notes that `item` of `krate` is public at `path`; of several such
    /// paths the shortest (then the first in order) names it.
    fn found_at(&mut self, krate: &str, item: &Value, path: &str) {
        if let Some(defined) = self.defined_at(krate, &item["id"]) {
            self.found_at_defined(defined, path);
        }
    }

    /// Notes that the item defined at `defined` is public at `path`.
    fn found_at_defined(&mut self, defined: String, path: &str) {
        let better = |old: &String| (path.len(), path) < (old.len(), old.as_str());
        if self.found.get(&defined).is_none_or(better) {
            self.found.insert(defined, path.to_string());
        }
    }

    fn module(&mut self, krate: &'static str, module: &Value, prefix: &str) {
        for id in module["items"].as_array().into_iter().flatten() {
            let Some(item) = self.item(krate, id) else {
                continue;
            };
            if let Some(use_) = item["inner"].get("use") {
                self.reexport(krate, use_, prefix);
            } else if let Some(name) = item["name"].as_str() {
                self.describe(krate, item, &format!("{prefix}::{name}"));
            }
        }
    }

    fn reexport(&mut self, krate: &'static str, use_: &Value, prefix: &str) {
        let name = use_["name"].as_str().unwrap_or("?");
        let path = format!("{prefix}::{name}");
        let target = &use_["id"];
        if use_["is_glob"] == true {
            match self.item(krate, target) {
                Some(m) if m["inner"].get("module").is_some() => {
                    self.module(krate, &m["inner"]["module"], prefix)
                }
                _ => self.add(
                    &format!("{prefix}::*"),
                    &format!("glob of {}", use_["source"]),
                ),
            }
            return;
        }
        if let Some(item) = self.item(krate, target) {
            self.describe(krate, item, &path);
        } else if let Some((home, item)) = self.foreign(krate, target) {
            self.describe(home, item, &path);
        } else {
            // Another crate's item (`Bytes`, the `Schema` trait): listed by
            // name only, but named in signatures by this path too.
            if let Some(defined) = self.defined_at(krate, target) {
                self.found_at_defined(defined, &path);
            }
            let source = use_["source"].as_str().unwrap_or("?");
            self.add(&path, &format!("re-export of {source}"));
        }
    }

    fn describe(&mut self, krate: &'static str, item: &Value, path: &str) {
        let Some((kind, body)) = item["inner"].as_object().and_then(|o| o.iter().next()) else {
            return;
        };
        self.found_at(krate, item, path);
        let sig = match kind.as_str() {
            "function" => self.function(krate, body),
            "constant" | "static" => format!(": {}", self.ty(krate, &body["type"])),
            "type_alias" => format!(
                "type{} = {}{}",
                self.params(krate, &body["generics"]),
                self.ty(krate, &body["type"]),
                self.where_clause(krate, &body["generics"])
            ),
            "struct" | "enum" | "union" => format!(
                "{}{}",
                self.params(krate, &body["generics"]),
                self.where_clause(krate, &body["generics"])
            ),
            "trait" => {
                let bounds = self.bounds(krate, &body["bounds"]);
                format!(
                    "{}{}{}",
                    self.params(krate, &body["generics"]),
                    if bounds.is_empty() {
                        String::new()
                    } else {
                        format!(": {bounds}")
                    },
                    self.where_clause(krate, &body["generics"])
                )
            }
            _ => String::new(),
        };
        self.add_sig(path, kind, &sig);
        match kind.as_str() {
            "module" => self.module(krate, body, path),
            "struct" => {
                for id in body["kind"]["plain"]["fields"]
                    .as_array()
                    .into_iter()
                    .flatten()
                {
                    self.field(krate, id, path, false);
                }
                self.tuple(krate, &body["kind"]["tuple"], path, false);
                self.impls(krate, body, path);
            }
            "enum" => {
                for id in body["variants"].as_array().into_iter().flatten() {
                    let Some(variant) = self.item(krate, id) else {
                        continue;
                    };
                    let name = variant["name"].as_str().unwrap_or("?");
                    let at = format!("{path}::{name}");
                    self.add(&at, "variant");
                    // A variant's fields are as public as the enum (rustdoc
                    // gives them no visibility of their own).
                    let kind = &variant["inner"]["variant"]["kind"];
                    for id in kind["struct"]["fields"].as_array().into_iter().flatten() {
                        self.field(krate, id, &at, true);
                    }
                    self.tuple(krate, &kind["tuple"], &at, true);
                }
                self.impls(krate, body, path);
            }
            "trait" => {
                for id in body["items"].as_array().into_iter().flatten() {
                    if let Some(member) = self.item(krate, id) {
                        let name = member["name"].as_str().unwrap_or("?");
                        let sig = self.member(krate, member);
                        self.add_sig(&format!("{path}::{name}"), "trait item", &sig);
                    }
                }
            }
            _ => {}
        }
    }

    fn field(&mut self, krate: &str, id: &Value, owner: &str, in_variant: bool) {
        if let Some(field) = self.item(krate, id) {
            if in_variant || field["visibility"] == "public" {
                let name = field["name"].as_str().unwrap_or("?");
                let ty = format!(": {}", self.ty(krate, &field["inner"]["struct_field"]));
                self.add_sig(&format!("{owner}::{name}"), "field", &ty);
            }
        }
    }

    /// A tuple struct's or variant's fields, by position (rustdoc gives
    /// `null` for a hidden one).
    fn tuple(&mut self, krate: &str, fields: &Value, owner: &str, in_variant: bool) {
        for (i, id) in fields.as_array().into_iter().flatten().enumerate() {
            let Some(field) = self.item(krate, id) else {
                continue;
            };
            if in_variant || field["visibility"] == "public" {
                let ty = format!(": {}", self.ty(krate, &field["inner"]["struct_field"]));
                self.add_sig(&format!("{owner}::{i}"), "field", &ty);
            }
        }
    }

    fn impls(&mut self, krate: &str, body: &Value, path: &str) {
        for id in body["impls"].as_array().into_iter().flatten() {
            let Some(imp) = self.item(krate, id).map(|i| &i["inner"]["impl"]) else {
                continue;
            };
            if imp["is_synthetic"] == true || !imp["blanket_impl"].is_null() {
                continue;
            }
            // `path` since rustdoc's JSON format 40 (Rust 1.86), `name` before.
            let trait_path = imp["trait"]["path"].as_str();
            match trait_path.or(imp["trait"]["name"].as_str()) {
                Some(t) => {
                    let t = t.rsplit("::").next().unwrap_or(t);
                    // The compiler's mark of a derived `PartialEq`, not a
                    // promise of ours.
                    if t != "StructuralPartialEq" {
                        self.add(path, &format!("impl {t}"));
                    }
                }
                None => {
                    for id in imp["items"].as_array().into_iter().flatten() {
                        let Some(member) = self.item(krate, id) else {
                            continue;
                        };
                        if member["visibility"] != "public" {
                            continue;
                        }
                        let kind = member["inner"]
                            .as_object()
                            .and_then(|o| o.keys().next())
                            .map_or("?", String::as_str);
                        let name = member["name"].as_str().unwrap_or("?");
                        let mut sig = self.member(krate, member);
                        if kind == "function" {
                            sig.push_str(&self.impl_context(krate, imp));
                        }
                        self.add_sig(&format!("{path}::{name}"), kind, &sig);
                    }
                }
            }
        }
    }
}

/// Signatures as text, from rustdoc's JSON (`rustdoc_types`, format 57 as
/// Rust 1.95 writes it). What it does not know it shows as `?kind`, so a
/// new form of type changes lines rather than failing the walk.
impl Lister<'_> {
    /// A method's or a trait item's signature: functions as
    /// [`Lister::function`], constants their type, associated types their
    /// bounds and value.
    fn member(&self, krate: &str, member: &Value) -> String {
        let Some((kind, body)) = member["inner"].as_object().and_then(|o| o.iter().next()) else {
            return String::new();
        };
        match kind.as_str() {
            "function" => self.function(krate, body),
            "assoc_const" => format!("const: {}", self.ty(krate, &body["type"])),
            "assoc_type" => {
                let mut out = format!("type{}", self.params(krate, &body["generics"]));
                let bounds = self.bounds(krate, &body["bounds"]);
                if !bounds.is_empty() {
                    out.push_str(&format!(": {bounds}"));
                }
                if !body["type"].is_null() {
                    out.push_str(&format!(" = {}", self.ty(krate, &body["type"])));
                }
                out + &self.where_clause(krate, &body["generics"])
            }
            _ => String::new(),
        }
    }

    /// `async fn<T: Bound>(&self, u32) -> T where ...`: the qualifiers,
    /// generics, parameter types (not their names) and return type.
    fn function(&self, krate: &str, f: &Value) -> String {
        let header = &f["header"];
        let mut out = String::new();
        for (flag, word) in [
            ("is_const", "const "),
            ("is_async", "async "),
            ("is_unsafe", "unsafe "),
        ] {
            if header[flag] == true {
                out.push_str(word);
            }
        }
        out.push_str(&self.abi(&header["abi"]));
        out.push_str("fn");
        out.push_str(&self.params(krate, &f["generics"]));
        out.push_str(&self.signature(krate, &f["sig"]));
        out.push_str(&self.where_clause(krate, &f["generics"]));
        out
    }

    /// `extern "C" ` for a foreign ABI, nothing for Rust's.
    fn abi(&self, abi: &Value) -> String {
        match abi {
            Value::String(s) if s == "Rust" => String::new(),
            Value::String(s) => format!("extern {s:?} "),
            Value::Object(o) => o
                .keys()
                .next()
                .map_or(String::new(), |k| format!("extern {k:?} ")),
            _ => String::new(),
        }
    }

    /// `(&self, u32) -> T` of a function signature.
    fn signature(&self, krate: &str, sig: &Value) -> String {
        let mut inputs: Vec<String> = sig["inputs"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|input| {
                let ty = &input[1];
                if input[0] != "self" {
                    return self.ty(krate, ty);
                }
                let reference = &ty["borrowed_ref"];
                match (&ty["generic"], &reference["type"]["generic"]) {
                    (Value::String(s), _) if s == "Self" => "self".to_string(),
                    (_, Value::String(s)) if s == "Self" => format!(
                        "&{}{}self",
                        reference["lifetime"]
                            .as_str()
                            .map_or(String::new(), |l| format!("{l} ")),
                        if reference["is_mutable"] == true {
                            "mut "
                        } else {
                            ""
                        }
                    ),
                    _ => format!("self: {}", self.ty(krate, ty)),
                }
            })
            .collect();
        if sig["is_c_variadic"] == true {
            inputs.push("...".to_string());
        }
        let mut out = format!("({})", inputs.join(", "));
        if !sig["output"].is_null() {
            out.push_str(&format!(" -> {}", self.ty(krate, &sig["output"])));
        }
        out
    }

    /// ` in impl<T: Clone> pulicast::SettingChanges<T>` for a method of an
    /// impl with bounds, or for a type other than the plain one (`impl
    /// Client<Req, Rep, ()>`); nothing for a plain `impl<T> Setting<T>`.
    fn impl_context(&self, krate: &str, imp: &Value) -> String {
        let generics = &imp["generics"];
        let params: Vec<&Value> = generics["params"]
            .as_array()
            .into_iter()
            .flatten()
            .collect();
        let bounded = params.iter().any(|p| {
            let kind = &p["kind"];
            kind["type"]["bounds"]
                .as_array()
                .is_some_and(|b| !b.is_empty())
                || kind["lifetime"]["outlives"]
                    .as_array()
                    .is_some_and(|b| !b.is_empty())
        });
        let wheres = generics["where_predicates"]
            .as_array()
            .is_some_and(|w| !w.is_empty());
        // The plain type names its parameters in order, as they are declared.
        let names: Vec<&str> = params.iter().filter_map(|p| p["name"].as_str()).collect();
        let args: Vec<Option<&str>> = imp["for"]["resolved_path"]["args"]["angle_bracketed"]
            ["args"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|a| a["type"]["generic"].as_str().or(a["lifetime"].as_str()))
            .collect();
        let plain =
            args.len() == names.len() && args.iter().zip(&names).all(|(a, n)| *a == Some(*n));
        if plain && !bounded && !wheres {
            return String::new();
        }
        format!(
            " in impl{} {}{}",
            self.params(krate, generics),
            self.ty(krate, &imp["for"]),
            self.where_clause(krate, generics)
        )
    }

    /// A type as a person writes it.
    fn ty(&self, krate: &str, t: &Value) -> String {
        let (kind, v) = match t {
            Value::String(s) if s == "infer" => return "_".to_string(),
            Value::Object(o) if o.len() == 1 => o.iter().next().expect("one entry"),
            Value::Null => return "?".to_string(),
            _ => return "?type".to_string(),
        };
        let list = |v: &Value| -> Vec<String> {
            v.as_array()
                .into_iter()
                .flatten()
                .map(|t| self.ty(krate, t))
                .collect()
        };
        match kind.as_str() {
            "resolved_path" => self.path(krate, v),
            "generic" | "primitive" => v.as_str().unwrap_or("?").to_string(),
            "borrowed_ref" => format!(
                "&{}{}{}",
                v["lifetime"]
                    .as_str()
                    .map_or(String::new(), |l| format!("{l} ")),
                if v["is_mutable"] == true { "mut " } else { "" },
                self.ty(krate, &v["type"])
            ),
            "raw_pointer" => format!(
                "*{} {}",
                if v["is_mutable"] == true {
                    "mut"
                } else {
                    "const"
                },
                self.ty(krate, &v["type"])
            ),
            "slice" => format!("[{}]", self.ty(krate, v)),
            "array" => format!(
                "[{}; {}]",
                self.ty(krate, &v["type"]),
                v["len"].as_str().unwrap_or("?")
            ),
            "tuple" => match list(v).as_slice() {
                [one] => format!("({one},)"),
                all => format!("({})", all.join(", ")),
            },
            "impl_trait" => format!("impl {}", self.bounds(krate, v)),
            "dyn_trait" => {
                let mut parts: Vec<String> = v["traits"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .map(|p| {
                        format!(
                            "{}{}",
                            self.for_lifetimes(krate, &p["generic_params"]),
                            self.path(krate, &p["trait"])
                        )
                    })
                    .collect();
                parts.extend(v["lifetime"].as_str().map(str::to_string));
                format!("dyn {}", parts.join(" + "))
            }
            "qualified_path" => {
                let name = v["name"].as_str().unwrap_or("?");
                let args = self.args(krate, &v["args"]);
                let on = self.ty(krate, &v["self_type"]);
                match &v["trait"] {
                    Value::Null => format!("{on}::{name}{args}"),
                    tr => format!("<{on} as {}>::{name}{args}", self.path(krate, tr)),
                }
            }
            "function_pointer" => {
                let header = &v["header"];
                format!(
                    "{}{}{}fn{}",
                    self.for_lifetimes(krate, &v["generic_params"]),
                    if header["is_unsafe"] == true {
                        "unsafe "
                    } else {
                        ""
                    },
                    self.abi(&header["abi"]),
                    self.signature(krate, &v["sig"])
                )
            }
            "pat" => self.ty(krate, &v["type"]),
            other => format!("?{other}"),
        }
    }

    /// A path to a type or trait, with its generic arguments: by its public
    /// path in the listed crate if it has one, else where it is defined.
    fn path(&self, krate: &str, p: &Value) -> String {
        let written = p["path"].as_str().unwrap_or("?");
        let name = match self.defined_at(krate, &p["id"]) {
            Some(defined) => match self.names.get(&defined) {
                Some(public) => public.clone(),
                // The standard library's modules move between releases
                // (`std::net::SocketAddr` is defined in
                // `core::net::socket_addr`): its items go by their name
                // alone, so a new toolchain leaves the listing as it is.
                None if ["core::", "alloc::", "std::"]
                    .iter()
                    .any(|c| defined.starts_with(c)) =>
                {
                    format!("std::{}", defined.rsplit("::").next().unwrap_or(&defined))
                }
                None => defined.clone(),
            },
            None => written.to_string(),
        };
        name + &self.args(krate, &p["args"])
    }

    /// `<T, Item = U>` or `(A) -> B`; nothing for no arguments.
    fn args(&self, krate: &str, args: &Value) -> String {
        let Some((kind, v)) = args.as_object().and_then(|o| o.iter().next()) else {
            return match args {
                Value::String(s) if s == "return_type_notation" => "(..)".to_string(),
                _ => String::new(),
            };
        };
        match kind.as_str() {
            "angle_bracketed" => {
                let mut all: Vec<String> = v["args"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .map(|a| match a {
                        Value::String(s) if s == "infer" => "_".to_string(),
                        _ => match a.as_object().and_then(|o| o.iter().next()) {
                            Some((k, x)) if k == "lifetime" => {
                                x.as_str().unwrap_or("?").to_string()
                            }
                            Some((k, x)) if k == "type" => self.ty(krate, x),
                            Some((k, x)) if k == "const" => {
                                x["expr"].as_str().unwrap_or("?").to_string()
                            }
                            _ => "?arg".to_string(),
                        },
                    })
                    .collect();
                for c in v["constraints"].as_array().into_iter().flatten() {
                    let name = format!(
                        "{}{}",
                        c["name"].as_str().unwrap_or("?"),
                        self.args(krate, &c["args"])
                    );
                    let binding = &c["binding"];
                    all.push(if let Some(term) = binding.get("equality") {
                        match term.get("type") {
                            Some(t) => format!("{name} = {}", self.ty(krate, t)),
                            None => format!(
                                "{name} = {}",
                                term["constant"]["expr"].as_str().unwrap_or("?")
                            ),
                        }
                    } else {
                        format!("{name}: {}", self.bounds(krate, &binding["constraint"]))
                    });
                }
                match all.is_empty() {
                    true => String::new(),
                    false => format!("<{}>", all.join(", ")),
                }
            }
            "parenthesized" => {
                let inputs: Vec<String> = v["inputs"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .map(|t| self.ty(krate, t))
                    .collect();
                let output = match &v["output"] {
                    Value::Null => String::new(),
                    t => format!(" -> {}", self.ty(krate, t)),
                };
                format!("({}){output}", inputs.join(", "))
            }
            other => format!("?{other}"),
        }
    }

    /// `Clone + ?Sized + 'a`.
    fn bounds(&self, krate: &str, bounds: &Value) -> String {
        let all: Vec<String> = bounds
            .as_array()
            .into_iter()
            .flatten()
            .map(|b| match b.as_object().and_then(|o| o.iter().next()) {
                Some((k, v)) if k == "trait_bound" => {
                    let modifier = match v["modifier"].as_str() {
                        Some("maybe") => "?",
                        Some("maybe_const") => "~const ",
                        _ => "",
                    };
                    format!(
                        "{}{modifier}{}",
                        self.for_lifetimes(krate, &v["generic_params"]),
                        self.path(krate, &v["trait"])
                    )
                }
                Some((k, v)) if k == "outlives" => v.as_str().unwrap_or("?").to_string(),
                Some((k, v)) if k == "use" => {
                    let captured: Vec<&str> = v
                        .as_array()
                        .into_iter()
                        .flatten()
                        .filter_map(|a| a["lifetime"].as_str().or(a["param"].as_str()))
                        .collect();
                    format!("use<{}>", captured.join(", "))
                }
                _ => "?bound".to_string(),
            })
            .collect();
        all.join(" + ")
    }

    /// `for<'a> ` of higher-ranked bounds; nothing without.
    fn for_lifetimes(&self, krate: &str, params: &Value) -> String {
        match self.param_list(krate, params).as_slice() {
            [] => String::new(),
            all => format!("for<{}> ", all.join(", ")),
        }
    }

    /// `<'a, T: Bound = Default, const N: usize>` of declared generics
    /// (those `impl Trait` arguments make are shown there); nothing without.
    fn params(&self, krate: &str, generics: &Value) -> String {
        match self.param_list(krate, &generics["params"]).as_slice() {
            [] => String::new(),
            all => format!("<{}>", all.join(", ")),
        }
    }

    fn param_list(&self, krate: &str, params: &Value) -> Vec<String> {
        params
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|p| {
                let name = p["name"].as_str().unwrap_or("?");
                let (kind, v) = p["kind"].as_object().and_then(|o| o.iter().next())?;
                Some(match kind.as_str() {
                    "lifetime" => {
                        let outlives = strings(&v["outlives"]);
                        match outlives.is_empty() {
                            true => name.to_string(),
                            false => format!("{name}: {}", outlives.join(" + ")),
                        }
                    }
                    "type" if v["is_synthetic"] == true => return None,
                    "type" => {
                        let mut out = name.to_string();
                        let bounds = self.bounds(krate, &v["bounds"]);
                        if !bounds.is_empty() {
                            out.push_str(&format!(": {bounds}"));
                        }
                        if !v["default"].is_null() {
                            out.push_str(&format!(" = {}", self.ty(krate, &v["default"])));
                        }
                        out
                    }
                    "const" => {
                        let mut out = format!("const {name}: {}", self.ty(krate, &v["type"]));
                        if let Some(default) = v["default"].as_str() {
                            out.push_str(&format!(" = {default}"));
                        }
                        out
                    }
                    other => format!("?{other} {name}"),
                })
            })
            .collect()
    }

    /// ` where T: Bound, 'a: 'b`; nothing without.
    fn where_clause(&self, krate: &str, generics: &Value) -> String {
        let all: Vec<String> = generics["where_predicates"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|w| match w.as_object().and_then(|o| o.iter().next()) {
                Some((k, v)) if k == "bound_predicate" => format!(
                    "{}{}: {}",
                    self.for_lifetimes(krate, &v["generic_params"]),
                    self.ty(krate, &v["type"]),
                    self.bounds(krate, &v["bounds"])
                ),
                Some((k, v)) if k == "lifetime_predicate" => {
                    let outlives = strings(&v["outlives"]);
                    format!(
                        "{}: {}",
                        v["lifetime"].as_str().unwrap_or("?"),
                        outlives.join(" + ")
                    )
                }
                Some((k, v)) if k == "eq_predicate" => {
                    let rhs = match v["rhs"].get("type") {
                        Some(t) => self.ty(krate, t),
                        None => v["rhs"]["constant"]["expr"]
                            .as_str()
                            .unwrap_or("?")
                            .to_string(),
                    };
                    format!("{} = {rhs}", self.ty(krate, &v["lhs"]))
                }
                _ => "?predicate".to_string(),
            })
            .collect();
        match all.is_empty() {
            true => String::new(),
            false => format!(" where {}", all.join(", ")),
        }
    }
}

fn listing(docs: &HashMap<&'static str, Value>, krate: &'static str) -> String {
    let doc = &docs[krate];
    let root = &doc["index"][doc["root"].to_string().trim_matches('"')];
    // The first walk finds where each item is public, the second names
    // the types in signatures by it.
    let mut names = HashMap::new();
    let mut lines = BTreeSet::new();
    for _ in 0..2 {
        let mut lister = Lister {
            docs,
            lines: BTreeSet::new(),
            names,
            found: HashMap::new(),
        };
        lister.module(krate, &root["inner"]["module"], krate);
        names = lister.found;
        lines = lister.lines;
    }
    let mut out = String::new();
    for line in lines {
        out.push_str(&line);
        out.push('\n');
    }
    out
}

/// The strings of a JSON array (lifetimes a bound names); none for
/// anything else.
fn strings(v: &Value) -> Vec<&str> {
    v.as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_str)
        .collect()
}

fn check(listed: &str, file: &Path, problems: &mut Vec<String>) {
    let checked_in = std::fs::read_to_string(file).unwrap_or_default();
    if listed == checked_in {
        return;
    }
    if std::env::var_os("PULICAST_BLESS").is_some() {
        std::fs::write(file, listed).expect("the listing is writable");
        return;
    }
    let old: BTreeSet<&str> = checked_in.lines().collect();
    let new: BTreeSet<&str> = listed.lines().collect();
    let mut diff = String::new();
    for gone in old.difference(&new) {
        diff.push_str(&format!("  - {gone}\n"));
    }
    for added in new.difference(&old) {
        diff.push_str(&format!("  + {added}\n"));
    }
    problems.push(format!("{} is not the surface:\n{diff}", file.display()));
}

#[test]
fn the_public_surface_is_the_one_checked_in() {
    let docs = rustdoc_json();
    let mut problems = Vec::new();
    for (krate, dir) in [("pulicast", "pulicast-rs"), ("pulicast_proto", "proto")] {
        let file = workspace().join(dir).join("public-api.txt");
        check(&listing(&docs, krate), &file, &mut problems);
    }
    assert!(
        problems.is_empty(),
        "{}\nIf the change is meant, run this test with PULICAST_BLESS=1, commit the \
         listings and say why in docs/architecture.md (\"The public surface\").",
        problems.join("\n")
    );
}

/// The internals stay internal: the one public module of `pulicast` is
/// its `text` facade (and the derive's hidden paths). This holds without
/// rustdoc, so it fails first and plainly when a `pub mod` comes back.
#[test]
fn pulicast_declares_no_public_module_but_text() {
    let lib = std::fs::read_to_string(workspace().join("pulicast-rs/src/lib.rs"))
        .expect("lib.rs is readable");
    for line in lib.lines().map(str::trim) {
        if let Some(rest) = line.strip_prefix("pub mod ") {
            let name = rest.trim_end_matches([';', ' ', '{']);
            assert!(
                name == "text" || name == "__private",
                "lib.rs makes module {name:?} public: give what users need a deliberate \
                 home instead (docs/architecture.md, \"The public surface\")"
            );
        }
        for module in ["proto", "wire", "pulicast_proto", "pulicast_proto::wire"] {
            assert!(
                !line.starts_with(&format!("pub use {module};"))
                    && line != format!("pub use pulicast_proto as {module};"),
                "lib.rs re-exports the core's module: {line:?}"
            );
        }
    }
}

/// The tools and the bridge use `pulicast`'s public API; only the files
/// that speak the wire itself (and say why) may import the core crate or
/// the discovery crate.
#[test]
fn the_tools_and_the_bridge_import_the_core_only_where_they_speak_the_wire() {
    let allowed = [
        // Shows service frames (calls, replies, progress) as a sniffer must.
        ("tools/src/sniff.rs", "pulicast_proto"),
        // Fake 2.x heartbeats and gossip for the discovery benchmark.
        ("tools/src/bench/discovery.rs", "pulicast_proto"),
        ("tools/src/bench/discovery.rs", "pulicast_discovery"),
        // MCAP schemas of the 2.x message types, from their ZCM definitions.
        ("tools/src/record.rs", "pulicast_proto"),
    ];
    let mut found = Vec::new();
    // The Python package's native module, too: bindings are users.
    for dir in ["tools/src", "bridge/src", "python/src", "web/src"] {
        let mut stack = vec![workspace().join(dir)];
        while let Some(path) = stack.pop() {
            if path.is_dir() {
                for entry in std::fs::read_dir(&path).expect("a source directory") {
                    stack.push(entry.expect("a directory entry").path());
                }
            } else if path.extension().is_some_and(|e| e == "rs") {
                let text = std::fs::read_to_string(&path).expect("a source file");
                let rel = path
                    .strip_prefix(workspace())
                    .expect("inside")
                    .to_path_buf();
                let rel = rel.to_string_lossy().replace('\\', "/");
                for krate in ["pulicast_proto", "pulicast_discovery"] {
                    let names = text
                        .lines()
                        .filter(|l| !l.trim_start().starts_with("//"))
                        .any(|l| l.contains(krate));
                    if names && !allowed.contains(&(rel.as_str(), krate)) {
                        found.push(format!("{rel} uses {krate}"));
                    }
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "these use an internal crate instead of pulicast's API: {found:?}"
    );
    let bridge = std::fs::read_to_string(workspace().join("bridge/Cargo.toml")).expect("toml");
    let deps = bridge
        .split("[dev-dependencies]")
        .next()
        .unwrap_or_default();
    for krate in ["pulicast-proto", "pulicast-discovery"] {
        assert!(
            !deps.contains(krate),
            "the bridge depends on {krate}: it should need pulicast's API alone"
        );
    }
}

/// Every item at `pulicast`'s root is accounted for in
/// `docs/architecture.md` ("The public surface" says why each is public),
/// so a new item fails here until the account names it. Read from the
/// checked-in listing, which the test above keeps true.
#[test]
fn every_root_item_is_accounted_for_in_the_architecture() {
    let listing = std::fs::read_to_string(workspace().join("pulicast-rs/public-api.txt"))
        .expect("the listing is readable");
    let doc = std::fs::read_to_string(workspace().join("docs/architecture.md"))
        .expect("architecture.md is readable");
    let section = doc
        .split("\n## The public surface\n")
        .nth(1)
        .and_then(|rest| rest.split("\n## ").next())
        .expect("architecture.md has a section \"The public surface\"");
    let roots: BTreeSet<&str> = listing
        .lines()
        .filter_map(|line| line.strip_prefix("pulicast::"))
        .filter_map(|rest| rest.split_once(' '))
        .map(|(name, _)| name)
        .filter(|name| !name.contains("::") && *name != "text")
        .collect();
    assert!(
        roots.len() > 50,
        "the listing names few root items: {roots:?}"
    );
    let unaccounted: Vec<&str> = roots
        .into_iter()
        .filter(|name| !section.contains(&format!("`{name}`")))
        .collect();
    assert!(
        unaccounted.is_empty(),
        "these are public at pulicast's root but docs/architecture.md (\"The public \
         surface\") does not say why: {unaccounted:?}"
    );
}

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

/// Walks one crate's public surface into lines `path kind`.
struct Lister<'a> {
    docs: &'a HashMap<&'static str, Value>,
    lines: BTreeSet<String>,
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
            let source = use_["source"].as_str().unwrap_or("?");
            self.add(&path, &format!("re-export of {source}"));
        }
    }

    fn describe(&mut self, krate: &'static str, item: &Value, path: &str) {
        let Some((kind, body)) = item["inner"].as_object().and_then(|o| o.iter().next()) else {
            return;
        };
        self.add(path, kind);
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
                        self.add(&format!("{path}::{name}"), "trait item");
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
                self.add(&format!("{owner}::{name}"), "field");
            }
        }
    }

    /// A tuple struct's or variant's fields, by position (rustdoc gives
    /// `null` for a hidden one).
    fn tuple(&mut self, krate: &str, fields: &Value, owner: &str, in_variant: bool) {
        for (i, id) in fields.as_array().into_iter().flatten().enumerate() {
            let visible = self
                .item(krate, id)
                .is_some_and(|f| in_variant || f["visibility"] == "public");
            if visible {
                self.add(&format!("{owner}::{i}"), "field");
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
                        self.add(&format!("{path}::{name}"), kind);
                    }
                }
            }
        }
    }
}

fn listing(docs: &HashMap<&'static str, Value>, krate: &'static str) -> String {
    let mut lister = Lister {
        docs,
        lines: BTreeSet::new(),
    };
    let doc = &docs[krate];
    let root = &doc["index"][doc["root"].to_string().trim_matches('"')];
    lister.module(krate, &root["inner"]["module"], krate);
    let mut out = String::new();
    for line in lister.lines {
        out.push_str(&line);
        out.push('\n');
    }
    out
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
    for dir in ["tools/src", "bridge/src"] {
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

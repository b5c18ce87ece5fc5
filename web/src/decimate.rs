//! What the page plots of a channel, decimated on the server (sans-IO:
//! no clock, no socket; the caller stamps and ticks). Each decoded
//! message's numeric leaves (`pose.x`, `ranges[2]`; a bool as 0 or 1; a
//! message that is one number as `value`) go into the current bucket,
//! which keeps, per field, the last value and the least and greatest;
//! [`Decimator::take`] ends the bucket. Ticked every
//! [`crate::channels::TICK`], a channel at any rate costs a client at
//! most one bucket per tick: a 1 kHz channel is shown at 30 points a
//! second, each with the extremes it stands for.
//!
//! Bounded by the server's choice, whatever the messages hold: at most
//! [`MAX_FIELDS`] fields a channel (the first seen; the rest counted),
//! at most [`MAX_LEAVES`] values looked at in a message, paths longer
//! than [`MAX_PATH`] bytes left out (counted), and the message shown as
//! JSON cut at
//! [`MAX_SHOWN`] bytes and sent at most every [`SHOW_EVERY_MS`].

use std::collections::HashMap;

use serde_json::{json, Map, Value};

/// Most fields plotted of one channel.
pub const MAX_FIELDS: usize = 32;

/// Most values looked at in one message, of any kind (an array of
/// thousands of numbers is no plot).
pub const MAX_LEAVES: usize = 1024;

/// Longest field path, in bytes.
pub const MAX_PATH: usize = 128;

/// Longest message shown as JSON, in bytes; a longer one is sent as
/// `{"longer_than": MAX_SHOWN}` (written no further than that).
pub const MAX_SHOWN: usize = 16 << 10;

/// The message shown is sent again at most this often (milliseconds).
pub const SHOW_EVERY_MS: f64 = 200.0;

#[derive(Debug, Clone, Copy)]
struct Agg {
    last: f64,
    min: f64,
    max: f64,
}

/// One channel's buckets.
#[derive(Debug, Default)]
pub struct Decimator {
    /// Field paths in the order first seen, at most [`MAX_FIELDS`].
    fields: Vec<String>,
    index: HashMap<String, usize>,
    /// This bucket's aggregate of each field (by index), if it has one.
    bucket: Vec<Option<Agg>>,
    /// Messages in this bucket, and when the last came (ms).
    n: u64,
    t: f64,
    /// Fields seen beyond [`MAX_FIELDS`] (in this bucket).
    left_out: usize,
    /// Messages of this bucket counted but not decoded.
    undecoded: u64,
    /// The newest message, and when one was last shown.
    last: Option<Value>,
    shown_at: Option<f64>,
}

impl Decimator {
    /// An empty decimator.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a message received at `t_ms` (milliseconds since the epoch).
    pub fn push(&mut self, t_ms: f64, value: Value) {
        self.n += 1;
        self.t = t_ms;
        let mut leaves = 0;
        let mut path = String::new();
        self.walk(&value, &mut path, &mut leaves);
        self.last = Some(value);
    }

    /// Counts a message that is not decoded (too large), shown as
    /// `shown`.
    pub fn push_opaque(&mut self, t_ms: f64, shown: Value) {
        self.n += 1;
        self.t = t_ms;
        self.last = Some(shown);
    }

    /// Counts a message not decoded for want of time (more came in this
    /// bucket than the server decodes): in `n` and `undecoded`, not in
    /// the extremes.
    pub fn skip(&mut self, t_ms: f64) {
        self.n += 1;
        self.undecoded += 1;
        self.t = t_ms;
    }

    fn walk(&mut self, value: &Value, path: &mut String, leaves: &mut usize) {
        if *leaves >= MAX_LEAVES {
            return;
        }
        *leaves += 1;
        let leaf = match value {
            Value::Number(n) => n.as_f64().filter(|v| v.is_finite()),
            Value::Bool(b) => Some(f64::from(u8::from(*b))),
            Value::Object(fields) => {
                for (key, inner) in fields {
                    if *leaves >= MAX_LEAVES {
                        break;
                    }
                    let at = path.len();
                    if !path.is_empty() {
                        path.push('.');
                    }
                    path.push_str(key);
                    self.walk(inner, path, leaves);
                    path.truncate(at);
                }
                None
            }
            Value::Array(items) => {
                for (i, inner) in items.iter().enumerate() {
                    if *leaves >= MAX_LEAVES {
                        break;
                    }
                    let at = path.len();
                    path.push_str(&format!("[{i}]"));
                    self.walk(inner, path, leaves);
                    path.truncate(at);
                }
                None
            }
            Value::String(_) | Value::Null => None,
        };
        let Some(v) = leaf else {
            return;
        };
        let name = match path.is_empty() {
            true => "value",
            false => path.as_str(),
        };
        // A path too long to show is left out, counted: cut, two of them
        // could merge into one field.
        if name.len() > MAX_PATH {
            self.left_out += 1;
            return;
        }
        let i = match self.index.get(name) {
            Some(&i) => i,
            None if self.fields.len() < MAX_FIELDS => {
                self.fields.push(name.to_string());
                self.bucket.push(None);
                self.index.insert(name.to_string(), self.fields.len() - 1);
                self.fields.len() - 1
            }
            None => {
                self.left_out += 1;
                return;
            }
        };
        let agg = self.bucket[i].get_or_insert(Agg {
            last: v,
            min: v,
            max: v,
        });
        agg.last = v;
        agg.min = agg.min.min(v);
        agg.max = agg.max.max(v);
    }

    /// Ends the bucket: `None` if no message came in it, else
    /// `{"t", "n", "v": {field: [last, min, max]}, "left_out"?, "last"?}`,
    /// where `t` is when its last message came and `last` (the newest
    /// message, at most every [`SHOW_EVERY_MS`]) is the message to show.
    pub fn take(&mut self) -> Option<Value> {
        if self.n == 0 {
            return None;
        }
        let mut values = Map::new();
        for (name, agg) in self.fields.iter().zip(self.bucket.iter_mut()) {
            if let Some(a) = agg.take() {
                values.insert(name.clone(), json!([a.last, a.min, a.max]));
            }
        }
        let mut out = json!({ "t": self.t, "n": self.n, "v": values });
        if self.left_out > 0 {
            out["left_out"] = json!(self.left_out);
        }
        if self.undecoded > 0 {
            out["undecoded"] = json!(self.undecoded);
        }
        let due = self
            .shown_at
            .is_none_or(|at| self.t - at >= SHOW_EVERY_MS || self.t < at);
        if due {
            if let Some(last) = self.last.take() {
                out["last"] = match fits(&last, MAX_SHOWN) {
                    true => last,
                    false => json!({ "longer_than": MAX_SHOWN }),
                };
                self.shown_at = Some(self.t);
            }
        }
        self.n = 0;
        self.left_out = 0;
        self.undecoded = 0;
        Some(out)
    }
}

/// Whether `value` as JSON takes at most `limit` bytes: written no
/// further than that to tell.
pub(crate) fn fits(value: &Value, limit: usize) -> bool {
    struct Upto(usize);
    impl std::io::Write for Upto {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0 = self
                .0
                .checked_sub(buf.len())
                .ok_or_else(|| std::io::Error::other("longer"))?;
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    serde_json::to_writer(Upto(limit), value).is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_thousand_messages_make_one_point_with_their_extremes() {
        let mut d = Decimator::new();
        assert_eq!(d.take(), None, "no message, no bucket");
        for i in 0..1000 {
            let x = f64::from(i % 100);
            d.push(
                1000.0 + f64::from(i) / 1000.0,
                json!({"pose": {"x": x, "ok": i % 2 == 0}, "name": "r"}),
            );
        }
        let b = d.take().unwrap();
        assert_eq!(b["n"], 1000);
        assert_eq!(b["v"]["pose.x"], json!([99.0, 0.0, 99.0]));
        assert_eq!(b["v"]["pose.ok"], json!([0.0, 0.0, 1.0]));
        assert!(b["v"].get("name").is_none(), "text is not plotted");
        assert_eq!(b["last"]["pose"]["x"], 99.0);
        assert_eq!(d.take(), None, "the bucket is emptied");
    }

    #[test]
    fn a_number_is_its_own_field_and_arrays_are_indexed() {
        let mut d = Decimator::new();
        d.push(0.0, json!(2.5));
        assert_eq!(d.take().unwrap()["v"]["value"], json!([2.5, 2.5, 2.5]));
        let mut d = Decimator::new();
        d.push(0.0, json!({"ranges": [1, 2, 3]}));
        let b = d.take().unwrap();
        assert_eq!(b["v"]["ranges[2]"], json!([3.0, 3.0, 3.0]));
    }

    #[test]
    fn fields_and_leaves_are_bounded_whatever_a_message_holds() {
        let mut d = Decimator::new();
        let wide: Map<String, Value> = (0..5000).map(|i| (format!("f{i}"), json!(i))).collect();
        d.push(0.0, Value::Object(wide));
        let b = d.take().unwrap();
        assert_eq!(b["v"].as_object().unwrap().len(), MAX_FIELDS);
        // The object itself is one of the values looked at.
        assert_eq!(b["left_out"], MAX_LEAVES - 1 - MAX_FIELDS);
        // Values that are no numbers count too: a list of a million nulls
        // is looked at no further than the bound.
        let mut d = Decimator::new();
        d.push(0.0, Value::Array(vec![Value::Null; 1_000_000]));
        assert_eq!(d.take().unwrap()["v"], json!({}));
        // Two long paths that begin alike are not merged: left out.
        let (a, b) = ("k".repeat(MAX_PATH) + "a", "k".repeat(MAX_PATH) + "b");
        let mut d = Decimator::new();
        d.push(0.0, json!({ a: 1, b: 2, "short": 3 }));
        let bucket = d.take().unwrap();
        assert_eq!(bucket["v"], json!({"short": [3.0, 3.0, 3.0]}));
        assert_eq!(bucket["left_out"], 2);
    }

    #[test]
    fn the_message_shown_is_cut_and_sent_at_most_five_times_a_second() {
        let mut d = Decimator::new();
        d.push(0.0, json!({"x": 1}));
        assert!(d.take().unwrap().get("last").is_some());
        d.push(33.0, json!({"x": 2}));
        assert!(d.take().unwrap().get("last").is_none(), "33 ms later");
        d.push(250.0, json!({"x": 3}));
        assert_eq!(d.take().unwrap()["last"]["x"], 3);
        let mut d = Decimator::new();
        d.push(0.0, json!({"blob": "z".repeat(MAX_SHOWN)}));
        assert_eq!(
            d.take().unwrap()["last"],
            json!({ "longer_than": MAX_SHOWN })
        );
        assert!(fits(&json!("z".repeat(10)), 12) && !fits(&json!("z".repeat(11)), 12));
    }
}

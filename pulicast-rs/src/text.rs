//! Messages as text: any payload shown as JSON by the type its channel
//! announces in discovery, and JSON turned back into a payload of that
//! type. This is how `puli-sniffer`, `puli publish` and the recorder read
//! and write messages whose types they were not compiled with.
//!
//! ```
//! use pulicast::{text, type_info_of, Schema};
//! #[derive(serde::Serialize, serde::Deserialize, Schema)]
//! struct Twist { linear: f64, angular: f64 }
//!
//! // What a publisher of `Twist` announces, and a payload it sends:
//! let info = type_info_of::<Twist>();
//! let schema = text::schema_of(&info).expect("a well-formed description");
//! let json = serde_json::json!({"linear": 0.5, "angular": -1.0});
//! let payload = text::encode_native_value(&schema, info.fingerprint, &json).unwrap();
//!
//! // A tool that knows only the announcement reads it back:
//! let shown = text::decode_payload(&payload, Some(&info));
//! assert_eq!(shown.type_name, "Twist");
//! assert_eq!(shown.value, json);
//! ```

pub use pulicast_proto::text::MAX_SCHEMA_BYTES;

// The examples of items defined in the core crate live on their re-exports
// here, where they can name `pulicast::text` as a user does (see lib.rs).

/// A payload in text form: what [`decode_payload`] makes of it.
///
/// ```
/// use pulicast::{text, Primitive};
/// let mut payload = Vec::new();
/// Primitive::String("Go LEFT!".into()).encode(&mut payload);
/// let shown = text::decode_payload(&payload, None); // 2.x primitives need no announcement
/// assert_eq!(shown.type_name, "string_msg");
/// assert_eq!(shown.value, "Go LEFT!");
/// let odd = text::decode_payload(&[0xde, 0xad], None); // what decodes as nothing else
/// assert_eq!((odd.type_name.as_str(), &odd.value["hex"]), ("bytes", &"dead".into()));
/// ```
pub use pulicast_proto::text::Decoded;

/// Any payload as JSON, by the type its channel announces: how
/// `puli-sniffer` shows messages it was not compiled with.
///
/// ```no_run
/// # fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::text::decode_payload;
/// // The type the channel's publishers announce, if any does.
/// let announced = node.channel("/rover1/pose").publishers().into_iter()
///     .flat_map(|m| m.channels)
///     .find(|c| c.name == "rover1/pose")
///     .and_then(|c| c.message_type);
/// let mut poses = node.channel("/rover1/pose").subscribe_raw()?;
/// while let Some(m) = poses.recv_blocking() {
///     let shown = decode_payload(&m.value, announced.as_ref()); // never fails
///     println!("{} {}: {}", m.source, shown.type_name, shown.value);
/// }
/// # Ok(()) }
/// ```
pub use pulicast_proto::text::decode_payload;

/// Decodes a payload as [`decode_payload`] does, with the announced type's
/// description parsed once beforehand ([`schema_of`]), for a reader of
/// many payloads of one type; `None` where `decode_payload` would show
/// bytes (no type known here, or the payload does not fit its type), so a
/// reader that keeps raw payloads as they are makes no hex of them.
///
/// ```
/// use pulicast::{text, type_info_of, Schema};
/// #[derive(serde::Serialize, serde::Deserialize, Schema)]
/// struct Twist { linear: f64, angular: f64 }
///
/// let info = type_info_of::<Twist>();
/// let schema = text::schema_of(&info).expect("a well-formed description");
/// let json = serde_json::json!({"linear": 0.5, "angular": -1.0});
/// let payload = text::encode_native_value(&schema, info.fingerprint, &json).unwrap();
/// for _ in 0..3 {
///     let shown = text::decode_typed(&payload, Some((&info, &schema))).unwrap();
///     assert_eq!((shown.type_name.as_str(), &shown.value), ("Twist", &json));
/// }
/// assert!(text::decode_typed(b"a JPEG frame", None).is_none());
/// ```
pub use pulicast_proto::text::decode_typed;

/// The JSON Schema (draft 2020-12) of a native type's messages in JSON, as
/// [`decode_payload`] shows them and [`encode_native_value`] takes them:
/// what a form or a viewer builds its fields from.
///
/// ```
/// use pulicast::{text, type_info_of, Schema};
/// #[derive(serde::Serialize, serde::Deserialize, Schema)]
/// struct Twist { linear: f64, angular: f64 }
///
/// let schema = text::json_schema(&text::schema_of(&type_info_of::<Twist>()).unwrap());
/// assert_eq!(schema["title"], "Twist");
/// assert_eq!(schema["properties"]["linear"]["type"], "number");
/// assert_eq!(schema["required"], serde_json::json!(["linear", "angular"]));
/// ```
pub use pulicast_proto::text::json_schema;

/// The JSON Schema of an announced type's messages: a native type's by
/// its description, a 2.x primitive's as its value, another 2.x type known
/// here as an object of its members; `None` if neither.
///
/// ```
/// use pulicast::{text, type_info_of};
/// let schema = text::json_schema_of(&type_info_of::<f64>()).unwrap(); // a 2.x double_msg
/// assert_eq!((schema["type"].as_str(), schema["title"].as_str()), (Some("number"), Some("double_msg")));
/// ```
pub use pulicast_proto::text::json_schema_of;

/// JSON as a payload of the announced type: how `puli publish` sends what a
/// person types to typed subscribers.
///
/// ```
/// use pulicast::{text, type_info_of, Schema};
/// #[derive(serde::Serialize, serde::Deserialize, Schema)]
/// struct Twist { linear: f64, angular: f64 }
///
/// let info = type_info_of::<Twist>(); // as discovery announces it
/// let schema = text::schema_of(&info).expect("a well-formed description");
/// let json = serde_json::json!({"linear": 0.5, "angular": -1});
/// let payload = text::encode_native_value(&schema, info.fingerprint, &json)?;
/// // `Channel::publish_bytes(&payload)` sends the bytes `publish(&Twist { .. })` would.
/// assert_eq!(text::decode_payload(&payload, Some(&info)).value["angular"], -1.0);
/// let wrong = text::encode_native_value(&schema, info.fingerprint, &serde_json::json!({"linear": 1}));
/// assert!(wrong.is_err()); // says where and what (`ValueError`)
/// # Ok::<(), text::ValueError>(())
/// ```
pub use pulicast_proto::text::encode_native_value;

/// Lower-case hex of bytes, as tools show payloads and keys.
///
/// ```
/// use pulicast::text::{hex, unhex};
/// let bytes = [0x5e, 0x0a];
/// assert_eq!(hex(&bytes), "5e0a");
/// assert_eq!(unhex(&hex(&bytes)).as_deref(), Some(&bytes[..]));
/// ```
pub use pulicast_proto::text::hex;

/// The type description an announcement carries, to decode and encode its
/// messages by.
///
/// ```
/// use pulicast::{text, type_info_of, Schema};
/// #[derive(serde::Serialize, serde::Deserialize, Schema)]
/// struct Twist { linear: f64, angular: f64 }
///
/// let mut info = type_info_of::<Twist>();
/// assert_eq!(text::schema_of(&info).map(|s| s.name), Some("Twist".to_string()));
/// // Announcements come from the network: a broken one is refused, never a panic.
/// info.schema.truncate(3);
/// assert!(text::schema_of(&info).is_none());
/// ```
pub use pulicast_proto::text::schema_of;

/// Bytes from hex, as a person types them (`0x` allowed).
///
/// ```
/// use pulicast::text::unhex;
/// assert_eq!(unhex("0x5e0A"), Some(vec![0x5e, 0x0a]));
/// assert_eq!(unhex("5e 0a"), None); // no separators
/// assert_eq!(unhex("5e0"), None); // whole bytes only
/// ```
pub use pulicast_proto::text::unhex;

/// Why JSON does not fit a type description: where, and what.
///
/// ```
/// use pulicast::{text, type_info_of, Schema};
/// #[derive(serde::Serialize, serde::Deserialize, Schema)]
/// struct Twist { linear: f64, angular: f64 }
///
/// let info = type_info_of::<Twist>();
/// let schema = text::schema_of(&info).expect("a well-formed description");
/// let typed = serde_json::json!({"linear": "fast", "angular": 0});
/// let e = text::encode_native_value(&schema, info.fingerprint, &typed).unwrap_err();
/// eprintln!("{e}"); // "<path>: <problem>", to show the person who typed it
/// assert!(e.path.contains("linear"));
/// ```
pub use pulicast_proto::text::ValueError;

/// Whether a type travels as raw bytes (`Vec<u8>`, `[u8]`): no fingerprint,
/// no length, as [`Channel::publish_bytes`](crate::Channel::publish_bytes)
/// sends it.
///
/// ```
/// use pulicast::{text::is_raw_bytes, Schema};
/// assert!(is_raw_bytes(<Vec<u8>>::SCHEMA)); // a JPEG frame, as 2.x peers send it
/// assert!(!is_raw_bytes(<Vec<u16>>::SCHEMA));
/// assert!(!is_raw_bytes(String::SCHEMA));
/// ```
pub use pulicast_proto::wire::is_raw_bytes;

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

pub use pulicast_proto::text::{
    decode_payload, encode_native_value, hex, schema_of, unhex, Decoded, ValueError,
    MAX_SCHEMA_BYTES,
};
pub use pulicast_proto::wire::is_raw_bytes;

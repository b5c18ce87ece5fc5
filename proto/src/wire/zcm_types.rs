//! ZCM type definitions and the ZCM fingerprint algorithm.
//!
//! A ZCM fingerprint is computed from the struct definition, not from its
//! bytes: the struct's name, then for each member its primitive type name (if
//! primitive), its number of dimensions and each dimension's mode and size.
//! Member names are not part of it. Nested structs add their own fingerprint.
//! [`ZcmStruct::fingerprint`] reproduces every fingerprint of the reference
//! implementation (`pulicast_messages`), which [`KNOWN`] lists.
//!
//! ```
//! use pulicast_proto::wire::zcm::fingerprint;
//! use pulicast_proto::wire::zcm_types::PULICAST_NODE;
//! assert_eq!(PULICAST_NODE.fingerprint(), fingerprint::PULICAST_NODE);
//! ```

use super::Fingerprint;

/// The type of a member.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ZcmType {
    /// A primitive: `int8_t`, `int16_t`, `int32_t`, `int64_t`, `byte`, `float`,
    /// `double`, `string` or `boolean`.
    Primitive(&'static str),
    /// A nested struct.
    Struct(&'static ZcmStruct),
}

/// One array dimension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dim {
    /// A fixed number of elements.
    Fixed(usize),
    /// As many elements as the named earlier member says.
    Variable(&'static str),
}

/// One member of a struct.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ZcmMember {
    /// The member's name.
    pub name: &'static str,
    /// Its type.
    pub ty: ZcmType,
    /// Its dimensions: empty for a scalar.
    pub dims: &'static [Dim],
}

/// A ZCM struct definition.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ZcmStruct {
    /// The struct's short name, without package.
    pub name: &'static str,
    /// Its members, in declaration (and wire) order.
    pub members: &'static [ZcmMember],
}

impl ZcmStruct {
    /// The fingerprint this struct carries on the wire.
    pub fn fingerprint(&self) -> Fingerprint {
        Fingerprint(self.fingerprint_on_path(&mut Vec::new()).to_be_bytes())
    }

    fn fingerprint_on_path<'a>(&'a self, path: &mut Vec<&'a str>) -> u64 {
        if path.contains(&self.name) {
            return 0;
        }
        path.push(self.name);
        let mut hash = self.base_hash();
        for member in self.members {
            if let ZcmType::Struct(child) = member.ty {
                hash = hash.wrapping_add(child.fingerprint_on_path(path));
            }
        }
        path.pop();
        hash.rotate_left(1)
    }

    /// The hash of the definition alone, before nested fingerprints.
    fn base_hash(&self) -> u64 {
        let mut v = 0x1234_5678i64;
        v = step_str(v, self.name);
        for member in self.members {
            if let ZcmType::Primitive(name) = member.ty {
                v = step_str(v, name);
            }
            v = step(v, member.dims.len() as u8);
            for dim in member.dims {
                v = match dim {
                    Dim::Fixed(n) => step_str(step(v, 0), &n.to_string()),
                    Dim::Variable(by) => step_str(step(v, 1), by),
                };
            }
        }
        v as u64
    }
}

/// One byte into the hash: shift left 8, xor the (arithmetic) top bits back
/// in, add the byte as a signed char, as zcm-gen does.
fn step(v: i64, c: u8) -> i64 {
    ((v << 8) ^ (v >> 55)).wrapping_add(i64::from(c as i8))
}

/// A string: its length as one byte, then its bytes.
fn step_str(v: i64, s: &str) -> i64 {
    s.bytes().fold(step(v, s.len() as u8), step)
}

macro_rules! zcm_struct {
    ($(#[$doc:meta])* $konst:ident = $name:literal { $($member:literal : $ty:expr $(; [$($dim:expr),*])?),* $(,)? }) => {
        $(#[$doc])*
        pub static $konst: ZcmStruct = ZcmStruct {
            name: $name,
            members: &[$(ZcmMember { name: $member, ty: $ty, dims: &[$($($dim),*)?] }),*],
        };
    };
}

use ZcmType::Primitive as P;

zcm_struct!(/** `boolean_msg` */ BOOLEAN_MSG = "boolean_msg" { "value": P("boolean") });
zcm_struct!(/** `byte_msg` */ BYTE_MSG = "byte_msg" { "value": P("byte") });
zcm_struct!(/** `double_msg` */ DOUBLE_MSG = "double_msg" { "value": P("double") });
zcm_struct!(/** `float_msg`: declared with a double, as the reference does. */ FLOAT_MSG = "float_msg" { "value": P("double") });
zcm_struct!(/** `int8_msg` */ INT8_MSG = "int8_msg" { "value": P("int8_t") });
zcm_struct!(/** `int16_msg` */ INT16_MSG = "int16_msg" { "value": P("int16_t") });
zcm_struct!(/** `int32_msg` */ INT32_MSG = "int32_msg" { "value": P("int32_t") });
zcm_struct!(/** `int64_msg` */ INT64_MSG = "int64_msg" { "value": P("int64_t") });
zcm_struct!(/** `string_msg` */ STRING_MSG = "string_msg" { "value": P("string") });
zcm_struct!(/** `ping`: round-trip probe. */ PING = "ping" {
    "timestamp_ns": P("int64_t"),
    "sequence_nr": P("int64_t"),
    "payload_size": P("int64_t"),
    "payload": P("byte"); [Dim::Variable("payload_size")],
});
zcm_struct!(/** `poke_setting` (no members). */ POKE_SETTING = "poke_setting" {});
zcm_struct!(/** `reset_setting_to_default` (no members). */ RESET_SETTING_TO_DEFAULT = "reset_setting_to_default" {});
zcm_struct!(/** `unset_setting` (no members). */ UNSET_SETTING = "unset_setting" {});
zcm_struct!(/** `pulicast_channel`, one entry of a heartbeat. */ PULICAST_CHANNEL = "pulicast_channel" {
    "name": P("string"),
    "publishing_period_ns": P("int64_t"),
    "is_published": P("boolean"),
    "is_subscribed": P("boolean"),
});
zcm_struct!(/** `pulicast_node`, the heartbeat on `__nodes`. */ PULICAST_NODE = "pulicast_node" {
    "name": P("string"),
    "session_id": P("int64_t"),
    "num_channels": P("int16_t"),
    "channels": ZcmType::Struct(&PULICAST_CHANNEL); [Dim::Variable("num_channels")],
});
zcm_struct!(/** `roc_ack`: acknowledges a remote object call. */ ROC_ACK = "roc_ack" {
    "message": P("string"),
    "fingerprint": P("byte"); [Dim::Fixed(8)],
    "len": P("int16_t"),
    "value": P("byte"); [Dim::Variable("len")],
});

/// Every message type the reference implementation defines.
pub static KNOWN: [&ZcmStruct; 16] = [
    &BOOLEAN_MSG,
    &BYTE_MSG,
    &DOUBLE_MSG,
    &FLOAT_MSG,
    &INT8_MSG,
    &INT16_MSG,
    &INT32_MSG,
    &INT64_MSG,
    &STRING_MSG,
    &PING,
    &POKE_SETTING,
    &RESET_SETTING_TO_DEFAULT,
    &UNSET_SETTING,
    &PULICAST_CHANNEL,
    &PULICAST_NODE,
    &ROC_ACK,
];

/// The known struct with this fingerprint.
pub fn by_fingerprint(fp: Fingerprint) -> Option<&'static ZcmStruct> {
    // Computed once: a fingerprint walks its struct's members, and this
    // runs for every received payload a tool or a binding shows.
    static FINGERPRINTS: std::sync::OnceLock<Vec<Fingerprint>> = std::sync::OnceLock::new();
    let fingerprints = FINGERPRINTS.get_or_init(|| KNOWN.iter().map(|s| s.fingerprint()).collect());
    let at = fingerprints.iter().position(|f| *f == fp)?;
    KNOWN.get(at).copied()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_step_matches_zcm_gen() {
        assert_eq!(step(0x1234_5678, 8) as u64, 0x0000_0012_3456_7808);
        assert_eq!(step(i64::MIN, 0) as u64, 0xffff_ffff_ffff_ff00);
        assert_eq!(step(0, 0x80) as u64, 0xffff_ffff_ffff_ff80);
    }

    #[test]
    fn base_hash_trace_of_roc_ack() {
        assert_eq!(ROC_ACK.base_hash(), 0xbb2e_747c_4d12_e478);
        assert_eq!(PULICAST_NODE.base_hash(), 0x9e37_a83a_293a_ac14);
    }
}

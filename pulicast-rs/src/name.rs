//! Names: the core's rules ([`pulicast_proto::name`]), with the API's error.

pub use pulicast_proto::name::{
    group_for, in_namespace, is_hidden_channel, sdbm, GROUP_BASE, MAX_NAME_LEN,
};

use crate::Error;

/// Resolves `name` against `namespace` into a full channel name.
///
/// Returns [`Error::InvalidName`] if the name or the result is empty, longer
/// than [`MAX_NAME_LEN`] bytes, or contains non-ASCII or control characters.
///
/// ```
/// use pulicast::resolve_name;
/// assert_eq!(resolve_name("left_arm/pose", "rover1").unwrap(), "rover1/left_arm/pose");
/// assert_eq!(resolve_name("../rover2/pose", "rover1").unwrap(), "rover2/pose");
/// assert_eq!(resolve_name("/ctrl", "rover1/left_arm").unwrap(), "ctrl");
/// assert!(resolve_name("..", "rover1").is_err()); // that is the root, not a channel
/// ```
pub fn resolve_name(name: &str, namespace: &str) -> Result<String, Error> {
    Ok(pulicast_proto::name::resolve_name(name, namespace)?)
}

pub(crate) fn resolve_path(path: &str, namespace: &str) -> Result<String, Error> {
    Ok(pulicast_proto::name::resolve_path(path, namespace)?)
}

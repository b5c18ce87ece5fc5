//! "Did you mean": the known name nearest to one that names nothing, so a
//! typo fails with the name that was meant instead of a bare "not found".

/// The name of `known` nearest to `wanted`, if one is near enough to be a
/// typo of it: at most a third of its characters added, dropped, changed
/// or swapped (one at least). Ties go to the first in order of the names.
///
/// ```
/// use pulicast_tools::suggest::nearest;
/// let known = ["rover1/max_speed", "rover1/mode", "rover2/max_speed"];
/// assert_eq!(nearest("rover1/max_sped", known), Some("rover1/max_speed"));
/// assert_eq!(nearest("lidar/scan", known), None);
/// ```
pub fn nearest<'a>(wanted: &str, known: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    let most = (wanted.chars().count() / 3).max(1);
    let length = wanted.chars().count();
    known
        .into_iter()
        // A fleet of a stranger's hundreds of thousands of names costs a
        // bounded search: the first names that could be near enough.
        .filter(|k| k.len().abs_diff(wanted.len()) <= most * 4 && *k != wanted)
        .filter(|k| k.chars().count().abs_diff(length) <= most)
        .take(MAX_CANDIDATES)
        .map(|k| (strsim::damerau_levenshtein(wanted, k), k))
        .filter(|(d, _)| *d <= most)
        .min()
        .map(|(_, k)| k)
}

/// The most names a suggestion weighs.
pub const MAX_CANDIDATES: usize = 10_000;

/// `" (did you mean NAME?)"` for the nearest of `known`, or nothing.
pub fn did_you_mean<'a>(wanted: &str, known: impl IntoIterator<Item = &'a str>) -> String {
    match nearest(wanted, known) {
        Some(k) => format!(" (did you mean {k}?)"),
        None => String::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn typos_find_the_name_and_strangers_find_none() {
        let known = ["rover1/distance_to", "rover1/plan", "rover2/distance_to"];
        assert_eq!(
            nearest("rover1/distance", known),
            Some("rover1/distance_to")
        );
        assert_eq!(nearest("rover1/plna", known), Some("rover1/plan"));
        assert_eq!(
            nearest("rover3/distance_to", known),
            Some("rover1/distance_to")
        );
        assert_eq!(nearest("x", known), None);
        assert_eq!(
            nearest("rover1/plan", known),
            None,
            "itself is no suggestion"
        );
        assert_eq!(
            did_you_mean("rover1/pln", known),
            " (did you mean rover1/plan?)"
        );
        assert_eq!(did_you_mean("camera", known), "");
    }
}

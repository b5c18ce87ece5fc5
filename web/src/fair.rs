//! Choosing what a bounded list shows when the fleet announces more than
//! fits: channels by the members that announce them, services by their
//! servers. Sans-IO, so the choice is tested on its own.
//!
//! A choice by name would let whoever names things to sort first fill
//! the list; a choice by turns alone would let one owner's bulky items
//! take the bytes. So each owner first gets an equal share of the places
//! and of the bytes, taking its items in its own order while they fit
//! its share; what is left then goes by turns to whatever still fits.
//! An owner with thousands of items, or items made large, gets its share
//! and no more: it can't push another owner's first items out. Owners
//! beyond the number of places (a thousand forged members) dilute every
//! share: only keys tell real members from forged ones (see docs/web.md).

use std::collections::HashSet;

/// The names to show, in the order chosen: at most `places` of them and
/// `budget` in all by `cost`, from `owners` (each owner's names in the
/// order it wants them shown; a name may have several owners and is
/// shown once, charged to the owner whose turn took it).
pub fn choose(
    owners: Vec<Vec<&str>>,
    places: usize,
    budget: usize,
    cost: impl Fn(&str) -> usize,
) -> Vec<&str> {
    let n = owners.len();
    if n == 0 || places == 0 {
        return Vec::new();
    }
    let (share_places, share_budget) = ((places / n).max(1), budget / n);
    let mut taken: HashSet<&str> = HashSet::new();
    let mut chosen: Vec<&str> = Vec::new();
    let mut cursor = vec![0usize; n];
    let mut used = vec![(0usize, 0usize); n];
    let mut total = 0usize;

    // Shares: by turns, each owner's next name while it fits the owner's
    // share; the first that does not ends the owner's turns here.
    let mut active: Vec<usize> = (0..n).collect();
    while !active.is_empty() && chosen.len() < places {
        active.retain(|&o| {
            let list = &owners[o];
            while list.get(cursor[o]).is_some_and(|name| taken.contains(name)) {
                cursor[o] += 1;
            }
            let Some(&name) = list.get(cursor[o]) else {
                return false;
            };
            let c = cost(name);
            let (places_used, bytes_used) = used[o];
            if chosen.len() >= places
                || places_used >= share_places
                || bytes_used.saturating_add(c) > share_budget
                || total.saturating_add(c) > budget
            {
                return false;
            }
            taken.insert(name);
            chosen.push(name);
            cursor[o] += 1;
            used[o] = (places_used + 1, bytes_used + c);
            total += c;
            true
        });
    }

    // The rest, by turns: each owner's next name that fits what is left
    // (one too large is passed over, not the end of the owner's turns).
    let mut active: Vec<usize> = (0..n).collect();
    while !active.is_empty() && chosen.len() < places {
        active.retain(|&o| {
            let list = &owners[o];
            while let Some(&name) = list.get(cursor[o]) {
                cursor[o] += 1;
                if taken.contains(name) {
                    continue;
                }
                let c = cost(name);
                if total.saturating_add(c) > budget {
                    continue;
                }
                if chosen.len() >= places {
                    return false;
                }
                taken.insert(name);
                chosen.push(name);
                total += c;
                return true;
            }
            false
        });
    }
    chosen
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(prefix: &str, n: usize) -> Vec<String> {
        (0..n).map(|i| format!("{prefix}{i:05}")).collect()
    }

    fn refs(v: &[String]) -> Vec<&str> {
        v.iter().map(String::as_str).collect()
    }

    #[test]
    fn an_owner_with_thousands_of_names_takes_its_share_of_places_and_no_more() {
        let many = names("!", 5000);
        let owners = vec![refs(&many), vec!["a", "shared"], vec!["shared", "b"]];
        let chosen = choose(owners, 6, usize::MAX, |_| 1);
        for name in ["a", "shared", "b"] {
            assert!(chosen.contains(&name), "{chosen:?}");
        }
        assert_eq!(chosen.len(), 6);
        // Everything, with room for it: each name once.
        let owners = vec![refs(&many), vec!["a", "shared"], vec!["shared", "b"]];
        assert_eq!(choose(owners, 10_000, usize::MAX, |_| 1).len(), 5003);
    }

    #[test]
    fn bulky_names_first_in_every_order_do_not_take_the_bytes_of_the_others() {
        // 100 owners of one bulky item each, then one owner of a small
        // one; the bulky ones together are more than the budget.
        let bulky = names("!bulky", 100);
        let mut owners: Vec<Vec<&str>> = bulky.iter().map(|b| vec![b.as_str()]).collect();
        owners.push(vec!["rover/pose"]);
        let cost = |name: &str| {
            if name.starts_with("!bulky") {
                10_000
            } else {
                100
            }
        };
        let chosen = choose(owners, 1024, 384 * 1024, cost);
        assert!(chosen.contains(&"rover/pose"), "{chosen:?}");
        let spent: usize = chosen.iter().map(|n| cost(n)).sum();
        assert!(spent <= 384 * 1024);
        // What is left of the bytes still goes to the bulky ones.
        assert!(chosen.len() > 30, "{}", chosen.len());
    }

    #[test]
    fn what_is_left_goes_to_whatever_still_fits() {
        // One owner alone: its share is the whole budget; a name too large
        // for what is left is passed over, the next one taken.
        let owners = vec![vec!["big", "huge", "small"]];
        let cost = |name: &str| match name {
            "big" => 60,
            "huge" => 60,
            _ => 30,
        };
        assert_eq!(choose(owners, 10, 100, cost), ["big", "small"]);
    }

    #[test]
    fn nothing_to_choose_from_or_no_places_chooses_nothing() {
        assert!(choose(Vec::new(), 10, 10, |_| 1).is_empty());
        assert!(choose(vec![vec!["a"]], 0, 10, |_| 1).is_empty());
    }
}

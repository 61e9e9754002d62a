//! Who keeps a node's identity when two processes are started for it.
//!
//! Before a node publishes anything, and for as long as it runs, it says
//! its [`Claim`] on `control/claim/<id>` (0: the leader) and listens there.
//! Two processes started for one identity at the same moment hear each
//! other's claims, and both apply the same rule ([`Claim::yields_to`]):
//! one that holds the identity already (past its listening window, its
//! claims settled) keeps it; of two that claim it at once, the lower
//! random nonce; the other process ends naming it. The rule reads no
//! clock (a claim's `since` is only said), so of any number of twins
//! exactly one runs whatever the hosts' clocks say: each twin sees the same
//! claims. (Before, the earlier `since` kept it: a newcomer whose clock ran
//! behind could take an identity already held.)
//! A twin started after the run began is refused by the estimates it hears
//! on its own key as well (`formation_net::startup::refuse_twin`).
//!
//! Through a run, the leader and a standby that took the run over say a
//! claim to lead with their term (docs/model.md §14): of two that lead at
//! once, the one of the lower term stands down ([`Claim::outranked_by`]);
//! that decision compares no clock.

use serde::{Deserialize, Serialize};

/// The longest host name a claim carries (longer ones are cut).
pub const MAX_HOST_CHARS: usize = 64;

/// One process's claim to a node's identity.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Claim {
    /// The node: 0 the leader, else a follower's id.
    pub id: u32,
    /// When the process began to claim (its wall clock, ns since the Unix epoch).
    pub since_unix_ns: u64,
    /// A number drawn at random by the process: two claims made in the
    /// same nanosecond still differ, and a process knows its own.
    pub nonce: u64,
    /// Where the process runs, for the line that names it.
    pub pid: u32,
    pub host: String,
    /// A claim to lead during the run: the leader's term (0: a claim to an
    /// identity at the start).
    pub term: u32,
    /// Said by a process that holds the identity already (it kept it at
    /// the end of its listening window, or leads): a newcomer gives way to
    /// it, whatever the two hosts' clocks say.
    pub settled: bool,
}

impl Claim {
    pub fn new(id: u32, since_unix_ns: u64, nonce: u64, pid: u32, host: &str) -> Self {
        let host = host.chars().take(MAX_HOST_CHARS).collect();
        Self { id, since_unix_ns, nonce, pid, host, term: 0, settled: false }
    }

    /// This claim, as a claim to lead in `term` (the lead is held: settled).
    pub fn in_term(self, term: u32) -> Self {
        Self { term, settled: true, ..self }
    }

    /// This claim, said once the process kept the identity.
    pub fn settled(self) -> Self {
        Self { settled: true, ..self }
    }

    /// Whether `other`, another process's claim to lead heard during the
    /// run, outranks this one: a higher term, or the same term (two
    /// standbys that took over at once) and a lower nonce. No clock is
    /// compared: both processes order the two claims alike.
    pub fn outranked_by(&self, other: &Claim) -> bool {
        other.id == self.id
            && other.nonce != self.nonce
            && (other.term, u64::MAX - other.nonce) > (self.term, u64::MAX - self.nonce)
    }

    /// Whether this process, still in its listening window, gives way to
    /// `other`, a claim heard on this identity's key: another process's
    /// (another nonce) for the same id that holds it already (settled), or
    /// that claims it at the same time with a lower nonce. No clock is
    /// read: both processes order the two claims alike.
    pub fn yields_to(&self, other: &Claim) -> bool {
        other.id == self.id && other.nonce != self.nonce && (other.settled || other.nonce < self.nonce)
    }

    /// "process 4242 on host lab-3, claiming since 0.120 s before this one".
    pub fn describe(&self, relative_to: &Claim) -> String {
        let ahead = relative_to.since_unix_ns as f64 - self.since_unix_ns as f64;
        let when = match ahead {
            a if a >= 0.0 => format!("{:.3} s before this one", a / 1e9),
            a => format!("{:.3} s after this one", -a / 1e9),
        };
        format!("process {} on host {}, claiming since {when}", self.pid, self.host)
    }
}

/// Of the claims heard, the one this process (`mine`) gives way to: the
/// first of them all. None: this process keeps the identity.
pub fn winner<'a>(mine: &Claim, heard: impl IntoIterator<Item = &'a Claim>) -> Option<&'a Claim> {
    heard.into_iter().filter(|c| mine.yields_to(c)).min_by_key(|c| (!c.settled, c.nonce))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn claim(id: u32, since: u64, nonce: u64) -> Claim {
        Claim::new(id, since, nonce, 100 + nonce as u32, "h")
    }

    /// Of any set of twins that claim an identity at once, each applying
    /// the rule to the claims of the others, exactly one keeps it: the
    /// lower nonce, whatever their clocks say (`since` is only said).
    #[test]
    fn of_any_twins_exactly_one_keeps_the_identity() {
        let sets: [&[(u64, u64)]; 5] = [
            &[(10, 7), (20, 3)],
            &[(20, 3), (10, 7)],
            &[(10, 7), (10, 3)],
            &[(5, 1), (5, 2), (4, 9), (6, 0)],
            &[(1, 1)],
        ];
        for set in sets {
            let claims: Vec<Claim> = set.iter().map(|&(s, n)| claim(3, s, n)).collect();
            let keep: Vec<&Claim> = claims.iter().filter(|c| winner(c, &claims).is_none()).collect();
            assert_eq!(keep.len(), 1, "{set:?}: {keep:?} keep the identity");
            let first = claims.iter().min_by_key(|c| c.nonce).expect("one");
            assert_eq!(keep[0], first, "{set:?}");
            for c in claims.iter().filter(|c| *c != first) {
                assert_eq!(winner(c, &claims), Some(first), "{set:?}: {c:?} names the lowest nonce");
            }
        }
    }

    /// A process that already holds the identity (past its window: its
    /// claims are settled) keeps it against a newcomer whose clock runs
    /// behind by any amount, and whatever its nonce.
    #[test]
    fn a_newcomer_gives_way_to_the_one_that_holds_it_whatever_the_clocks() {
        let holder = claim(3, 10_000_000_000, 9).settled();
        let newcomer = claim(3, 1, 1);
        assert!(newcomer.yields_to(&holder), "a clock 10 s behind and a lower nonce change nothing");
        assert_eq!(winner(&newcomer, [&holder, &claim(3, 5, 0)]), Some(&holder), "the holder before a twin");
        assert!(claim(3, 0, 0).yields_to(&claim(0, 9, 9).in_term(1)) == false, "another id");
        assert!(claim(0, 0, 0).yields_to(&claim(0, 9, 9).in_term(1)), "a leader that leads holds the identity");
    }

    /// A process's own claim heard back, and claims to other ids, are not twins.
    #[test]
    fn its_own_claim_and_other_ids_are_no_twins() {
        let mine = claim(3, 10, 7);
        assert!(!mine.yields_to(&mine.clone()));
        assert!(!mine.yields_to(&claim(4, 1, 1)));
        assert!(mine.yields_to(&claim(3, 90, 6)), "a lower nonce, made later");
        assert!(!mine.yields_to(&claim(3, 9, 8)), "a higher nonce, made earlier");
    }

    /// Of leaders that claim the lead at once, whatever their clocks say,
    /// exactly one is outranked by none: the highest term, and of two of
    /// one term, the lower nonce.
    #[test]
    fn of_leaders_of_several_terms_exactly_one_leads_whatever_their_clocks() {
        let sets: [&[(u32, u64, u64)]; 4] = [
            &[(1, 10, 7), (2, 90, 3)],
            &[(1, 10, 3), (2, 5, 7)],
            &[(2, 10, 7), (2, 10, 3), (1, 0, 1)],
            &[(3, 99, 9), (1, 1, 1), (2, 50, 0)],
        ];
        for set in sets {
            let claims: Vec<Claim> = set.iter().map(|&(t, since, n)| claim(0, since, n).in_term(t)).collect();
            let lead: Vec<&Claim> = claims.iter().filter(|c| !claims.iter().any(|o| c.outranked_by(o))).collect();
            assert_eq!(lead.len(), 1, "{set:?}: {lead:?} lead");
            let best = claims.iter().max_by_key(|c| (c.term, u64::MAX - c.nonce)).expect("one");
            assert_eq!(lead[0], best, "{set:?}: the highest term, then the lower nonce");
        }
        let mine = claim(0, 10, 7).in_term(2);
        assert!(!mine.outranked_by(&mine.clone()), "its own claim heard back");
        assert!(!mine.outranked_by(&claim(3, 1, 1).in_term(9)), "another identity's");
    }

    #[test]
    fn a_claim_is_said_in_words_with_a_cut_host_name() {
        let long = "x".repeat(500);
        let c = Claim::new(3, 1_000_000_000, 1, 42, &long);
        assert_eq!(c.host.chars().count(), MAX_HOST_CHARS);
        let me = Claim::new(3, 1_120_000_000, 2, 43, "b");
        assert_eq!(c.describe(&me), format!("process 42 on host {}, claiming since 0.120 s before this one", c.host));
        let bytes = crate::codec::encode(&c);
        assert_eq!(crate::codec::decode::<Claim>(&bytes), Some(c));
        assert_eq!(crate::codec::decode::<Claim>(&bytes[..bytes.len() - 1]), None);
    }
}

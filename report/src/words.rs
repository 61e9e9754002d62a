//! Words in what the commands print.

/// "1 follower", "2 followers".
pub fn count(n: usize, word: &str) -> String {
    format!("{n} {word}{}", if n == 1 { "" } else { "s" })
}

#[cfg(test)]
mod tests {
    #[test]
    fn one_is_singular() {
        assert_eq!(
            (super::count(1, "link"), super::count(0, "link"), super::count(2, "edge")),
            ("1 link".to_string(), "0 links".to_string(), "2 edges".to_string())
        );
    }
}

//! The command line's own parsing: clap's errors as one line.

/// The command line parsed, or one line and exit status 2: clap's own
/// errors take 3–5 lines (the error, a tip, the usage, "For more
/// information"); they become the error and its tip on one line, with the
/// `--help` to ask. Help and version print as clap prints them.
pub fn parse_or_exit<T: clap::Parser>() -> T {
    use clap::error::ErrorKind;
    match T::try_parse() {
        Ok(t) => t,
        Err(e) => match e.kind() {
            ErrorKind::DisplayHelp
            | ErrorKind::DisplayVersion
            | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => e.exit(),
            _ => {
                eprintln!("{}", one_line(&e.render().to_string()));
                std::process::exit(2)
            }
        },
    }
}

/// clap's error text on one line: "error: …; tip: … (formation sim --help)".
fn one_line(text: &str) -> String {
    let mut parts = Vec::new();
    let mut help = None;
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        if let Some(usage) = line.strip_prefix("Usage:") {
            // "formation sim [OPTIONS] <SCENARIO>": the command's own words.
            let words: Vec<&str> = usage.split_whitespace().take_while(|w| !w.starts_with(['[', '<', '-'])).collect();
            help = Some(format!("{} --help", words.join(" ")));
        } else if !line.starts_with("For more information") {
            parts.push(line.to_string());
        }
    }
    let mut out = parts.join("; ").replace(":; ", ": ");
    if !out.starts_with("error:") {
        out = format!("error: {out}");
    }
    match help {
        Some(h) => format!("{out} ({h})"),
        None => out,
    }
}

#[cfg(test)]
mod tests {
    use super::one_line;

    #[test]
    fn clap_errors_become_one_line() {
        let text = "error: invalid value 'bogus' for '--robots <WHO>'\n  [possible values: simulated, stand-in, \
                    external]\n\nFor more information, try '--help'.\n";
        assert_eq!(
            one_line(text),
            "error: invalid value 'bogus' for '--robots <WHO>'; [possible values: simulated, stand-in, external]"
        );
        let text = "error: unexpected argument '--foo' found\n\n  tip: to pass '--foo' as a value, use '-- \
                    --foo'\n\nUsage: formation sim [OPTIONS] <SCENARIO>\n\nFor more information, try '--help'.\n";
        assert_eq!(
            one_line(text),
            "error: unexpected argument '--foo' found; tip: to pass '--foo' as a value, use '-- --foo' (formation \
             sim --help)"
        );
    }
}

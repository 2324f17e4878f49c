//! How every binary (`evermap-agent`, `evermap-server`, `evermap-demo`) reports the error it stops on:
//! the error, then each cause in its `source()` chain that the text above it does not already say.
//!
//! evermap's errors name what went wrong in evermap's terms and keep the library error that found it as
//! their `source()`; many also quote that error in their own message, so that a log line that prints
//! only the error (`{e}`) still says why. Printed as a plain chain, such a cause would appear twice.

use std::error::Error;
use std::fmt::Write as _;
use std::process::ExitCode;

/// The error and the causes its messages do not already contain, one per line under `Caused by:`
/// (the layout of `anyhow`'s report).
pub fn error_report(error: &(dyn Error + 'static)) -> String {
    let mut report = format!("Error: {error}");
    let mut said = error.to_string();
    let mut causes = Vec::new();
    let mut next = error.source();
    while let Some(cause) = next {
        let text = cause.to_string();
        if !said.contains(&text) {
            causes.push(text.clone());
        }
        said = text;
        next = cause.source();
    }
    if !causes.is_empty() {
        report.push_str("\n\nCaused by:");
        for (i, cause) in causes.iter().enumerate() {
            let _ = write!(report, "\n    {i}: {cause}");
        }
    }
    report
}

/// A `main`'s exit: success, or the [`error_report`] on standard error and exit code 1 (what Rust does
/// for a `main` that returns an error, without the repeated causes).
pub fn exit_code<E: AsRef<dyn Error + 'static>>(result: Result<(), E>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("{}", error_report(error.as_ref()));
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, thiserror::Error)]
    #[error("{what}")]
    struct Layer {
        what: String,
        #[source]
        source: Option<Box<dyn Error + Send + Sync>>,
    }

    fn layer(what: &str, source: Option<Layer>) -> Layer {
        Layer {
            what: what.to_owned(),
            source: source.map(|s| Box::new(s) as Box<dyn Error + Send + Sync>),
        }
    }

    #[test]
    fn a_cause_the_message_already_quotes_is_not_repeated() {
        let io = layer("unexpected end of file", None);
        let error = layer(
            "bag.db3: malformed rosbag2 sqlite3 data: unexpected end of file",
            Some(io),
        );
        assert_eq!(
            error_report(&error),
            "Error: bag.db3: malformed rosbag2 sqlite3 data: unexpected end of file"
        );
    }

    #[test]
    fn a_cause_the_message_does_not_say_is_listed_below_it() {
        let io = layer("permission denied", None);
        let error = layer(
            "reading the configuration",
            Some(layer(
                "config.toml: cannot open: permission denied",
                Some(io),
            )),
        );
        assert_eq!(
            error_report(&error),
            "Error: reading the configuration\n\nCaused by:\n    \
             0: config.toml: cannot open: permission denied"
        );
        assert_eq!(
            error_report(&layer("plain", None)),
            "Error: plain",
            "an error with no source is one line"
        );
    }
}

//! The log output of every binary (`evermap-agent`, `evermap-server`, `evermap-demo`): `tracing` events
//! formatted by `tracing-subscriber`, filtered by `RUST_LOG` when it is set and otherwise at the level the
//! command chose. Here because both sides link this crate and neither links the other.
//!
//! `RUST_LOG` takes `tracing-subscriber`'s `EnvFilter` directives: a level (`debug`), per-target levels
//! (`info,server::site=debug,zenoh=warn`), or a level inside one span (`info,[site{site=store-1}]=debug`:
//! everything one site's task logs). The server's spans: `site{site}` around each site task (and the
//! zenoh tasks of that site), `session{robot, session}` inside it around each request of a session, and
//! one per agent RPC (`open_session`, `upload`, `close_session`) with the site, robot and session asked
//! for. The agent's `run` runs its robot session in a `session{site, robot, session}` span
//! (`robot_agent::uplink::session_span`).

use std::io::IsTerminal as _;

use tracing_subscriber::EnvFilter;
use tracing_subscriber::filter::LevelFilter;
use tracing_subscriber::fmt::writer::BoxMakeWriter;

/// Where log lines go.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LogOutput {
    /// Standard output: a service's log (journald, a file).
    Stdout,
    /// Standard error: a tool whose standard output is its result (JSON lines, the demo's report).
    Stderr,
}

/// Installs the global subscriber: `RUST_LOG` when it is set and valid, else every target at `level`
/// (`LevelFilter::OFF`: silent unless `RUST_LOG` asks). An invalid `RUST_LOG` is reported (at WARN) and
/// ignored. Colours only on a terminal, and never with `NO_COLOR` set. Call once, first thing in `main`.
pub fn init_logging(level: LevelFilter, output: LogOutput) {
    let from_env = EnvFilter::try_from_default_env();
    // `try_from_default_env` fails both when RUST_LOG is unset and when it does not parse; only the
    // second is worth a word.
    let ignored = std::env::var_os(EnvFilter::DEFAULT_ENV)
        .is_some()
        .then(|| from_env.as_ref().err().map(ToString::to_string))
        .flatten();
    let filter = from_env.unwrap_or_else(|_| fallback_filter(level));
    let no_color = std::env::var_os("NO_COLOR").is_some();
    let (writer, ansi) = match output {
        LogOutput::Stdout => (
            BoxMakeWriter::new(std::io::stdout),
            std::io::stdout().is_terminal(),
        ),
        LogOutput::Stderr => (
            BoxMakeWriter::new(std::io::stderr),
            std::io::stderr().is_terminal(),
        ),
    };
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(writer)
        .with_ansi(ansi && !no_color)
        .init();
    if let Some(error) = ignored {
        tracing::warn!("RUST_LOG ignored ({error}): logging at {level}");
    }
}

/// Every target at `level`: what `with_max_level(level)` filtered before `RUST_LOG` was read.
pub fn fallback_filter(level: LevelFilter) -> EnvFilter {
    EnvFilter::default().add_directive(level.into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fallback_filters_at_the_commands_level() {
        for level in [LevelFilter::OFF, LevelFilter::INFO, LevelFilter::DEBUG] {
            assert_eq!(fallback_filter(level).max_level_hint(), Some(level));
        }
    }
}

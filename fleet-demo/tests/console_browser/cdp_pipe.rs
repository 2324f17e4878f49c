//! A headless Chromium driven through the Chrome DevTools Protocol over `--remote-debugging-pipe`.
//!
//! Why hand-written: the crates that drive Chromium (`headless_chrome`, `chromiumoxide`) talk CDP over a
//! WebSocket and compile the whole generated protocol (tens of thousands of lines, a WebSocket and HTTP
//! client stack) for the five commands this test sends. Over the pipe, CDP is JSON messages separated
//! by NUL bytes on file descriptors 3 (to the browser) and 4 (from it); `sh` maps the child's stdin and
//! stdout onto them (`exec chromium ... 3<&0 4>&1`), so no unsafe `pre_exec` is needed and no port is
//! opened. Every wait is bounded.

use std::io::{BufRead as _, BufReader, Write as _};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, sync_channel};
use std::time::{Duration, Instant};

use serde_json::{Value, json};

/// The Chromium binary: `EVERMAP_CHROMIUM`, else the first of `chromium`, `chromium-browser`,
/// `google-chrome` on the `PATH`.
pub fn find_chromium() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("EVERMAP_CHROMIUM") {
        return Some(PathBuf::from(path));
    }
    let path = std::env::var_os("PATH")?;
    for dir in std::env::split_paths(&path) {
        for name in ["chromium", "chromium-browser", "google-chrome"] {
            let candidate = dir.join(name);
            if candidate.is_file() {
                return Some(candidate);
            }
        }
    }
    None
}

/// A running headless Chromium with one page attached. Killed on drop.
pub struct Chromium {
    child: Child,
    to_browser: ChildStdin,
    messages: Receiver<Value>,
    next_id: u64,
    session: Option<String>,
    log: PathBuf,
}

impl Chromium {
    /// Starts Chromium (profile and log in `dir`) with a `width` × `height` window and attaches to a
    /// new blank page.
    pub fn launch(binary: &Path, dir: &Path, width: u32, height: u32) -> Result<Self, String> {
        let log = dir.join("chromium.log");
        let log_file = std::fs::File::create(&log).map_err(|e| e.to_string())?;
        let mut child = Command::new("sh")
            .arg("-c")
            .arg(r#"exec "$@" 3<&0 4>&1 </dev/null >/dev/null"#)
            .arg("sh")
            .arg(binary)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--no-default-browser-check",
                "--hide-scrollbars",
                "--mute-audio",
                "--remote-debugging-pipe",
            ])
            .arg(format!("--window-size={width},{height}"))
            .arg(format!("--user-data-dir={}", dir.join("profile").display()))
            .arg("about:blank")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(log_file)
            .spawn()
            .map_err(|e| format!("cannot start {}: {e}", binary.display()))?;
        let to_browser = child.stdin.take().ok_or("no pipe to the browser")?;
        let from_browser = child.stdout.take().ok_or("no pipe from the browser")?;
        let (sender, messages) = sync_channel(4096);
        std::thread::Builder::new()
            .name("cdp-reader".into())
            .spawn(move || {
                let mut reader = BufReader::new(from_browser);
                let mut buffer = Vec::new();
                // Ends at the browser's exit (EOF) or when the test is gone.
                while let Ok(n) = reader.read_until(0, &mut buffer) {
                    if n == 0 {
                        break;
                    }
                    if buffer.last() == Some(&0) {
                        buffer.pop();
                    }
                    if let Ok(message) = serde_json::from_slice::<Value>(&buffer)
                        && message.get("id").is_some()
                        && sender.send(message).is_err()
                    {
                        break;
                    }
                    buffer.clear();
                }
            })
            .map_err(|e| e.to_string())?;
        let mut browser = Self {
            child,
            to_browser,
            messages,
            next_id: 0,
            session: None,
            log,
        };
        let target = browser.call("Target.createTarget", json!({ "url": "about:blank" }))?;
        let target_id = target["targetId"].clone();
        let attached = browser.call(
            "Target.attachToTarget",
            json!({ "targetId": target_id, "flatten": true }),
        )?;
        browser.session = attached["sessionId"].as_str().map(str::to_owned);
        browser.call("Page.enable", json!({}))?;
        Ok(browser)
    }

    /// The browser's log so far (for failure messages).
    pub fn log_tail(&self) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let start = text.len().saturating_sub(2000);
        text.get(start..).unwrap_or_default().to_owned()
    }

    /// Sends one command (to the attached page once there is one) and waits up to 30 s for its result.
    pub fn call(&mut self, method: &str, params: Value) -> Result<Value, String> {
        self.next_id += 1;
        let id = self.next_id;
        let mut message = json!({ "id": id, "method": method });
        message["params"] = params;
        if let Some(session) = &self.session {
            message["sessionId"] = json!(session);
        }
        let mut bytes = message.to_string().into_bytes();
        bytes.push(0);
        self.to_browser
            .write_all(&bytes)
            .and_then(|()| self.to_browser.flush())
            .map_err(|e| format!("{method}: cannot write to the browser: {e}"))?;
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.messages.recv_timeout(left) {
                Ok(reply) if reply["id"] == json!(id) => {
                    if let Some(error) = reply.get("error") {
                        return Err(format!("{method}: {error}"));
                    }
                    return Ok(reply["result"].clone());
                }
                Ok(_) => {}
                Err(RecvTimeoutError::Timeout) => {
                    return Err(format!("{method}: no answer within 30 s"));
                }
                Err(RecvTimeoutError::Disconnected) => {
                    return Err(format!("{method}: the browser exited"));
                }
            }
        }
    }

    /// Opens `url` in the page.
    pub fn navigate(&mut self, url: &str) -> Result<(), String> {
        let result = self.call("Page.navigate", json!({ "url": url }))?;
        match result.get("errorText") {
            Some(error) => Err(format!("navigating to {url}: {error}")),
            None => Ok(()),
        }
    }

    /// Evaluates a JS expression in the page and returns its value (JSON).
    pub fn evaluate(&mut self, expression: &str) -> Result<Value, String> {
        let result = self.call(
            "Runtime.evaluate",
            json!({ "expression": expression, "returnByValue": true, "awaitPromise": true }),
        )?;
        if let Some(exception) = result.get("exceptionDetails") {
            return Err(format!("{expression}: {exception}"));
        }
        Ok(result["result"]["value"].clone())
    }

    /// A PNG screenshot of the page.
    pub fn screenshot(&mut self) -> Result<Vec<u8>, String> {
        use base64::Engine as _;
        let result = self.call("Page.captureScreenshot", json!({ "format": "png" }))?;
        let data = result["data"].as_str().ok_or("no screenshot data")?;
        base64::engine::general_purpose::STANDARD
            .decode(data)
            .map_err(|e| e.to_string())
    }
}

impl Drop for Chromium {
    fn drop(&mut self) {
        // Ask the browser to close (its renderers with it), then make sure.
        self.session = None;
        let _ = self.call("Browser.close", json!({}));
        for _ in 0..50 {
            if matches!(self.child.try_wait(), Ok(Some(_))) {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

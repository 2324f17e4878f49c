//! What the site publishes: its version and view after each change, and the same as a stored summary.

use std::sync::Arc;

use super::SiteTask;
use crate::site::VersionInfo;
use crate::site::site_summary::SiteSummary;

impl SiteTask {
    /// What the site publishes now, as its [`SiteSummary`] (`None` while unloaded).
    pub(super) fn summary(&self) -> Option<SiteSummary> {
        if self.unloaded || self.map.is_none() {
            return None;
        }
        Some(SiteSummary::of(
            *self.versions.borrow(),
            &self.views.borrow(),
        ))
    }

    pub(super) fn publish(&self) {
        if let Ok(map) = self.map() {
            let info = VersionInfo {
                version: map.version(),
                counts: map.counts(),
            };
            // The view first: whoever hears of the version finds it.
            self.views.send_replace(Arc::new(map.view()));
            self.versions.send_replace(info);
        }
    }
}

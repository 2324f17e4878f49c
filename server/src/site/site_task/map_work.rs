//! Where work on the site map runs: the blocking pool, or a maintenance thread for a session's end.

use super::SiteTask;
use crate::site::maintenance_thread::run_as_maintenance;
use crate::site::{SiteError, SiteMap};

impl SiteTask {
    /// Runs `f` on the map on the blocking pool and puts the map back.
    pub(super) async fn with_map_blocking<T: Send + 'static>(
        &mut self,
        f: impl FnOnce(&mut SiteMap) -> T + Send + 'static,
    ) -> Result<T, SiteError> {
        let mut map = self.map.take().ok_or_else(|| {
            SiteError::Internal("the site map was lost by a failed worker".into())
        })?;
        let (map, result) = tokio::task::spawn_blocking(move || {
            let result = f(&mut map);
            (map, result)
        })
        .await
        .map_err(SiteError::Worker)?;
        self.map = Some(map);
        Ok(result)
    }

    /// [`Self::with_map_blocking`] on a maintenance thread (see `maintenance_thread`): a session's end,
    /// which yields the CPU to robots' data. `what` names the work in errors.
    pub(super) async fn with_map_in_maintenance<T: Send + 'static>(
        &mut self,
        what: &'static str,
        f: impl FnOnce(&mut SiteMap) -> T + Send + 'static,
    ) -> Result<T, SiteError> {
        let mut map = self.map.take().ok_or_else(|| {
            SiteError::Internal("the site map was lost by a failed worker".into())
        })?;
        let (map, result) = run_as_maintenance(what, move || {
            let result = f(&mut map);
            (map, result)
        })
        .await?;
        self.map = Some(map);
        Ok(result)
    }
}

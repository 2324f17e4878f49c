//! An atomic group of writes to one site.

use crate::{
    MAX_ID_BYTES, MAX_VALUE_BYTES, RecordId, RecordKind, Result, StorageError, key,
    validate_session_id, validate_site_id,
};

/// One write of a [`WriteBatch`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BatchOp {
    /// Insert or overwrite a record.
    Put {
        /// Kind of the record.
        kind: RecordKind,
        /// Id of the record.
        id: RecordId,
        /// Opaque value (encoded by the caller).
        value: Vec<u8>,
    },
    /// Remove a record (no error if absent).
    Delete {
        /// Kind of the record.
        kind: RecordKind,
        /// Id of the record.
        id: RecordId,
    },
}

/// Writes to one site that [`crate::MapStore::apply`] performs all together or not at all.
///
/// Besides puts and deletes (applied in order, so a later op on the same key wins), a batch can
/// - bump the site's map version ([`WriteBatch::bump_map_version`]): the new version is stored in the same
///   atomic write as the records that make it;
/// - carry an upload's session sequence number ([`WriteBatch::for_session`]): the batch is applied only if the
///   number is greater than the session's last applied one, and that number is stored with it, so a re-sent
///   upload is applied exactly once.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WriteBatch {
    site: String,
    ops: Vec<BatchOp>,
    bump_map_version: bool,
    session: Option<(String, u64)>,
}

impl WriteBatch {
    /// An empty batch for `site` (applying an empty batch just registers the site).
    pub fn new(site: impl Into<String>) -> Self {
        Self {
            site: site.into(),
            ops: Vec::new(),
            bump_map_version: false,
            session: None,
        }
    }

    /// Adds a put of `value` at (kind, id).
    pub fn put(
        &mut self,
        kind: RecordKind,
        id: impl Into<RecordId>,
        value: impl Into<Vec<u8>>,
    ) -> &mut Self {
        self.ops.push(BatchOp::Put {
            kind,
            id: id.into(),
            value: value.into(),
        });
        self
    }

    /// Adds a delete of (kind, id).
    pub fn delete(&mut self, kind: RecordKind, id: impl Into<RecordId>) -> &mut Self {
        self.ops.push(BatchOp::Delete {
            kind,
            id: id.into(),
        });
        self
    }

    /// Makes the batch increment the site's map version by one.
    pub fn bump_map_version(&mut self) -> &mut Self {
        self.bump_map_version = true;
        self
    }

    /// Makes the batch conditional on `seq` being greater than the last applied sequence number of
    /// `session` on this site (gaps are allowed), and records `seq` as the new last applied one.
    pub fn for_session(&mut self, session: impl Into<String>, seq: u64) -> &mut Self {
        self.session = Some((session.into(), seq));
        self
    }

    /// The site.
    pub fn site(&self) -> &str {
        &self.site
    }

    /// The puts and deletes, in order.
    pub fn ops(&self) -> &[BatchOp] {
        &self.ops
    }

    /// Whether the batch bumps the map version.
    pub fn bumps_map_version(&self) -> bool {
        self.bump_map_version
    }

    /// The session and sequence number the batch is conditional on, if any.
    pub fn session(&self) -> Option<(&str, u64)> {
        self.session
            .as_ref()
            .map(|(session, seq)| (session.as_str(), *seq))
    }

    /// Number of puts and deletes.
    pub fn len(&self) -> usize {
        self.ops.len()
    }

    /// Whether the batch has no puts or deletes.
    pub fn is_empty(&self) -> bool {
        self.ops.is_empty()
    }

    /// Checks ids, sizes and names; stores call this before writing anything.
    pub fn validate(&self) -> Result<()> {
        validate_site_id(&self.site)?;
        if let Some((session, _)) = &self.session {
            validate_session_id(session)?;
        }
        for op in &self.ops {
            let (kind, id, value_len) = match op {
                BatchOp::Put { kind, id, value } => (*kind, id, value.len()),
                BatchOp::Delete { kind, id } => (*kind, id, 0),
            };
            let describe =
                || key::describe(&key::record_key(&self.site, kind.as_byte(), id.as_bytes()));
            if id.as_bytes().len() > MAX_ID_BYTES {
                return Err(StorageError::TooLarge {
                    key: describe(),
                    what: "id",
                    len: id.as_bytes().len(),
                    max: MAX_ID_BYTES,
                });
            }
            if value_len > MAX_VALUE_BYTES {
                return Err(StorageError::TooLarge {
                    key: describe(),
                    what: "value",
                    len: value_len,
                    max: MAX_VALUE_BYTES,
                });
            }
        }
        Ok(())
    }
}

/// What [`crate::MapStore::apply`] did with a batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchOutcome {
    /// The batch was written.
    Applied {
        /// The site's map version after the batch.
        map_version: u64,
    },
    /// The batch's session sequence number was not greater than the last applied one: nothing was written.
    Duplicate {
        /// The session's last applied sequence number.
        last_applied: u64,
    },
}

impl BatchOutcome {
    /// Whether the batch was written.
    pub fn is_applied(self) -> bool {
        matches!(self, Self::Applied { .. })
    }
}

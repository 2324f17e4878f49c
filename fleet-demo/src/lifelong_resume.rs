//! `evermap-demo lifelong --resume`: a long run (a hundred sessions take hours) continued where it stopped.
//!
//! After every session the run writes, beside `report.json`, its resume point into `OUT/resume/`: the
//! lifelong map as a site checkpoint (`checkpoint-K.pb`, the `SiteCheckpoint` the server restores sites
//! from, so the map comes back bit for bit) and `resume.json`, which names that checkpoint, the next
//! session, the frame the run scores in, the robot's dock and what the run was started with. The
//! checkpoint is written first and `resume.json` replaces the old one by a rename, so a run killed at any
//! point leaves a resume point that is whole (the last session's, or the one before). A resumed run must
//! be started with the same world, seed, policy, durations, dock starts and configuration, and is refused
//! by name otherwise; `--resume-under-new-config` lets the configuration differ (an A/B test of later
//! sessions from one resume point, which the report records).

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use mapping::geometry::Rigid2;
use mapping::lifelong::LifelongMap;
use prost::Message as _;
use proto::SiteCheckpoint;
use serde::{Deserialize, Serialize};

/// What a run was started with; a resumed run must be started with the same.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunIdentity {
    pub world: String,
    pub seed: u64,
    pub policy: String,
    pub session_duration_s: Option<f64>,
    pub mapping_duration_s: Option<f64>,
    pub dock_starts: bool,
    /// CRC-32 of the configuration's `Debug` form (every option, names and values).
    pub config_fingerprint: u32,
}

/// `OUT/resume/resume.json`.
#[derive(Debug, Serialize, Deserialize)]
struct ResumeFile {
    run: RunIdentity,
    /// The session the resumed run starts with (the last ended one's successor).
    next_session: u32,
    /// The checkpoint file of the map after session `next_session - 1`, in the same folder.
    checkpoint: String,
    /// Serialized as nalgebra does (the rotation's unit complex number): every bit comes back.
    world_from_map: Rigid2,
    dock: Option<Rigid2>,
}

/// What a resumed run starts from.
pub struct ResumePoint {
    /// The first session to run.
    pub next_session: u32,
    /// The map after the session before it.
    pub map: LifelongMap,
    /// The frame the run scores in (session 0's trajectory aligned to its truth).
    pub world_from_map: Rigid2,
    /// The robot's last pose of the session before, if that session was placed.
    pub dock: Option<Rigid2>,
    /// The configuration fingerprint the run was at the resume point (another one only where
    /// `other_config` allowed it).
    pub config_fingerprint: u32,
}

fn folder(out: &Path) -> PathBuf {
    out.join("resume")
}

/// Writes the resume point after session `session`: its map's checkpoint, then `resume.json` naming it
/// (renamed into place), then removes the checkpoint it replaces.
pub fn write(
    out: &Path,
    run: &RunIdentity,
    session: u32,
    map: &LifelongMap,
    world_from_map: &Rigid2,
    dock: Option<&Rigid2>,
) -> anyhow::Result<()> {
    let dir = folder(out);
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let name = format!("checkpoint-{session}.pb");
    let bytes = proto::pb::SiteCheckpoint::from(&SiteCheckpoint::of(map, 0, 0)).encode_to_vec();
    write_atomically(&dir.join(&name), &bytes)?;
    let previous = read_file(&dir).ok().map(|f| f.checkpoint);
    let file = ResumeFile {
        run: run.clone(),
        next_session: session + 1,
        checkpoint: name.clone(),
        world_from_map: *world_from_map,
        dock: dock.copied(),
    };
    write_atomically(
        &dir.join("resume.json"),
        (serde_json::to_string_pretty(&file)? + "\n").as_bytes(),
    )?;
    if let Some(previous) = previous.filter(|p| *p != name) {
        // Best effort: a leftover older checkpoint costs disk, not correctness.
        let _ = std::fs::remove_file(dir.join(previous));
    }
    Ok(())
}

fn write_atomically(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let temporary = path.with_extension("partial");
    std::fs::write(&temporary, bytes)
        .with_context(|| format!("cannot write {}", temporary.display()))?;
    std::fs::rename(&temporary, path).with_context(|| format!("cannot write {}", path.display()))
}

fn read_file(dir: &Path) -> anyhow::Result<ResumeFile> {
    let path = dir.join("resume.json");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{} is not a resume point", path.display()))
}

/// The resume point in `out`, checked against what this run was started with (its configuration too,
/// unless `other_config`); its map restored under `options`.
pub fn read(
    out: &Path,
    run: &RunIdentity,
    options: mapping::lifelong::LifelongOptions,
    other_config: bool,
) -> anyhow::Result<ResumePoint> {
    let dir = folder(out);
    let file = read_file(&dir)?;
    let expected = RunIdentity {
        config_fingerprint: if other_config {
            run.config_fingerprint
        } else {
            file.run.config_fingerprint
        },
        ..file.run.clone()
    };
    if expected != *run {
        anyhow::bail!(
            "{} was written by a run started with {:?}; this one is started with {:?}: resume it with the \
             same world, seed, policy, durations, dock starts and configuration",
            dir.display(),
            file.run,
            run
        );
    }
    let path = dir.join(&file.checkpoint);
    let bytes = std::fs::read(&path).with_context(|| format!("cannot read {}", path.display()))?;
    let pb = proto::pb::SiteCheckpoint::decode(bytes.as_slice())
        .with_context(|| format!("{} is not a checkpoint", path.display()))?;
    let checkpoint = SiteCheckpoint::try_from(&pb)
        .with_context(|| format!("{} cannot be read", path.display()))?;
    let map = checkpoint
        .restore(options)
        .with_context(|| format!("the map in {} cannot be restored", path.display()))?;
    Ok(ResumePoint {
        next_session: file.next_session,
        map,
        world_from_map: file.world_from_map,
        dock: file.dock,
        config_fingerprint: file.run.config_fingerprint,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use mapping::geometry::rigid2;

    fn identity() -> RunIdentity {
        RunIdentity {
            world: "store".into(),
            seed: 1,
            policy: "clt".into(),
            session_duration_s: Some(120.0),
            mapping_duration_s: None,
            dock_starts: false,
            config_fingerprint: 7,
        }
    }

    #[test]
    fn a_resume_point_is_read_back_and_refused_to_another_run() {
        let dir = tempfile::tempdir().unwrap();
        let options = mapping::lifelong::LifelongOptions::default();
        let map = LifelongMap::new(options.clone()).unwrap();
        let (frame, dock) = (rigid2(2.0, -1.0, 0.3), rigid2(10.0, 4.0, -2.0));
        write(dir.path(), &identity(), 3, &map, &frame, Some(&dock)).unwrap();
        let point = read(dir.path(), &identity(), options.clone(), false).unwrap();
        assert_eq!(point.next_session, 4);
        assert_eq!(point.world_from_map, frame);
        assert_eq!(point.dock, Some(dock));
        assert_eq!(point.map.counts(), map.counts());
        let other = RunIdentity {
            seed: 2,
            ..identity()
        };
        let refused = read(dir.path(), &other, options.clone(), false)
            .err()
            .expect("refused");
        assert!(
            refused.to_string().contains("same world, seed"),
            "{refused}"
        );
        // Another configuration is refused unless asked for, and then only the configuration may differ.
        let reconfigured = RunIdentity {
            config_fingerprint: 8,
            ..identity()
        };
        assert!(read(dir.path(), &reconfigured, options.clone(), false).is_err());
        let point = read(dir.path(), &reconfigured, options.clone(), true).unwrap();
        assert_eq!(point.config_fingerprint, 7);
        assert!(read(dir.path(), &other, options.clone(), true).is_err());
        // The next session's point replaces this one and its checkpoint.
        write(dir.path(), &identity(), 4, &map, &frame, None).unwrap();
        assert!(!dir.path().join("resume/checkpoint-3.pb").exists());
        let point = read(dir.path(), &identity(), options, false).unwrap();
        assert_eq!((point.next_session, point.dock), (5, None));
    }

    #[test]
    fn a_pose_keeps_its_bits_through_the_resume_file() {
        let pose = rigid2(1.0 / 3.0, -2.5e-7, 0.123_456_789);
        let json = serde_json::to_string(&pose).unwrap();
        let back: Rigid2 = serde_json::from_str(&json).unwrap();
        assert_eq!(back, pose);
    }
}

//! `evermap-demo simulate`: writes one session of the simulated changing store as a ROS1 bag, with its
//! ground truth as a TUM file beside it, so every tool can read it like a real recording.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::Args;
use robot_agent::map_image;
use robot_agent::source::write_bag;
use simulator::{SessionOptions, Store, World};

/// Arguments of `simulate`.
#[derive(Args)]
pub struct SimulateArgs {
    /// Which world: `store` (a realistic supermarket) or `aisles` (identical shelf rows, adversarial).
    #[arg(long, value_enum, default_value_t = World::Store)]
    world: World,
    /// Seed of the store layout and its change schedule.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Session (day) number: 0 is the mapping run over every aisle; later ones are cleaning runs from a
    /// random start with that day's layout.
    #[arg(long, default_value_t = 0)]
    session: u32,
    /// Length cap in seconds (session 0 default: the whole cleaning route, ~62 min in `store`, ~54 min in
    /// `aisles`; later sessions: 300 s).
    #[arg(long)]
    max_duration_s: Option<f64>,
    /// The bag to write; the truth goes to `<out>.truth.tum` and a picture of the day's layout (static
    /// structure black, what changes from day to day gray, the route red) to `<out>.layout.png`.
    #[arg(long)]
    out: PathBuf,
}

/// Runs the command.
pub fn run(args: &SimulateArgs) -> anyhow::Result<()> {
    let store = Store::generate(args.world.options(), args.seed)?;
    let mut options = SessionOptions::default();
    if let Some(t) = args.max_duration_s {
        options.max_duration_s = t;
        options.mapping_max_duration_s = t;
    }
    let session = store.session(args.session, &options)?;
    if let Some(parent) = args.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("cannot create {}", parent.display()))?;
    }
    let file = std::fs::File::create(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut writer = std::io::BufWriter::new(file);
    write_bag(&mut writer, &session.events, &session.base_from_laser)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    let mut truth_path = args.out.clone().into_os_string();
    truth_path.push(".truth.tum");
    let truth_file = std::fs::File::create(&truth_path)
        .with_context(|| format!("cannot create {}", truth_path.to_string_lossy()))?;
    mapping::io::tum::write_tum(std::io::BufWriter::new(truth_file), &session.ground_truth)?;
    let mut layout_path = args.out.clone().into_os_string();
    layout_path.push(".layout.png");
    let (w, h, pixels) = simulator::layout_to_rgb(&store, args.session, 0.05);
    map_image::write_rgb_png(std::path::Path::new(&layout_path), w, h, &pixels)?;
    println!(
        "{}",
        serde_json::json!({
            "bag": args.out.display().to_string(),
            "truth": truth_path.to_string_lossy(),
            "layout": layout_path.to_string_lossy(),
            "world": args.world.name(),
            "events": session.events.len(),
            "scans": session.ground_truth.len(),
            "duration_s": session.duration_s,
            "distance_m": session.distance_m,
        })
    );
    Ok(())
}

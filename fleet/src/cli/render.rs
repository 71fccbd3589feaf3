//! `fleet render`: a frame of a `(frames, rows, cols)` `.npy` as a PNG (viridis, colour bar),
//! or the whole sequence as a GIF.

use fleet::plot::{self, Panel};
use fleet_exit::bad_input;
use fleet_math::process::dataset;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct Args {
    /// A float64 .npy of shape (frames, rows, cols).
    input: PathBuf,
    /// Frame to draw (PNG). Several: --frame 0 --frame 50 --frame 99 stacks them.
    #[arg(long, default_values_t = [0usize])]
    frame: Vec<usize>,
    /// Draw every frame into an animated GIF instead.
    #[arg(long)]
    gif: bool,
    /// Milliseconds per GIF frame.
    #[arg(long, default_value_t = 80)]
    delay_ms: u32,
    /// Output image (.png, or .gif with --gif).
    #[arg(long)]
    out: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let ext = args
        .out
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match (args.gif, ext.as_deref()) {
        (true, Some("gif")) | (false, Some("png")) => {}
        (true, _) => {
            return Err(bad_input(anyhow::anyhow!(
                "--out {}: --gif writes a GIF, name it .gif",
                args.out.display()
            )))
        }
        (false, _) => {
            return Err(bad_input(anyhow::anyhow!(
                "--out {}: a frame is written as PNG, name it .png (or give --gif and .gif)",
                args.out.display()
            )))
        }
    }
    let field = dataset::load(&args.input, 1.0).map_err(bad_input)?;
    let (n, frames) = (field.dim(), field.frames());
    let name = args
        .input
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_default();
    let columns: Vec<Vec<f64>> = (0..frames)
        .map(|k| field.snapshots.col(k).iter().copied().collect())
        .collect();
    let panel = |k: usize| Panel {
        values: &columns[k],
        rows: field.rows,
        cols: field.cols,
        title: format!("{name}  frame {k}/{}", frames - 1),
        disks: vec![],
    };
    if args.gif {
        let all: Vec<Panel> = (0..frames).map(panel).collect();
        let range = plot::range_of(&all);
        let pb = super::progress_bar(frames as u64, "gif");
        plot::gif(
            &args.out,
            (0..frames).map(|k| vec![panel(k)]),
            range,
            args.delay_ms,
            || pb.inc(1),
        )?;
        pb.finish_and_clear();
    } else {
        if let Some(&k) = args.frame.iter().find(|&&k| k >= frames) {
            return Err(bad_input(anyhow::anyhow!(
                "--frame {k} out of range: {} has frames 0..{}",
                args.input.display(),
                frames - 1
            )));
        }
        let panels: Vec<Panel> = args.frame.iter().map(|&k| panel(k)).collect();
        plot::png(&args.out, &panels, None)?;
    }
    println!("wrote {} ({} cells per frame)", args.out.display(), n);
    Ok(())
}

//! Redraws the `quincunx trade` charts of every report in a directory (the `<label>.json`
//! files `--plot` wrote), measuring nothing:
//! `cargo run --release -p quincunx-repo-tools --example replot -- <dir>`.

fn main() -> anyhow::Result<()> {
    let dir = std::env::args_os()
        .nth(1)
        .ok_or_else(|| anyhow::anyhow!("usage: replot <directory of trade reports>"))?;
    quincunx_repo_tools::trade::replot(std::path::Path::new(&dir))
}

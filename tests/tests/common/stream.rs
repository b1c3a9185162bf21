//! Helpers of the streaming tests: a killable server, details read from a local copy of
//! a repository, the converged reference cut, and frame loops with cut checks.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::DVec3;
use quincunx_client::dag::{Dag, Half};
use quincunx_client::domain::{Domain, World};
use quincunx_client::flight;
use quincunx_client::refine::{Availability, DetailSource, Refinement, SystemClock};
use quincunx_client::session::Session;
use quincunx_client::view::View;
use quincunx_server::{RepoConfig, Server, ServerConfig};
use quincunx_store::Repository;

/// A server on its own single-worker runtime: dropping it kills it abruptly.
pub struct Served {
    pub addr: SocketAddr,
    runtime: Option<tokio::runtime::Runtime>,
}

impl Served {
    pub fn start(addr: SocketAddr, repos: Vec<RepoConfig>) -> Served {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .unwrap();
        let config = ServerConfig {
            addr,
            repos,
            workers: 1,
            ..Default::default()
        };
        // A restarted server may find the old repository lock still held for a moment.
        let deadline = Instant::now() + Duration::from_secs(10);
        let server = loop {
            match runtime.block_on(Server::bind(config.clone())) {
                Ok(s) => break s,
                Err(e) if Instant::now() < deadline => {
                    eprintln!("bind: {e}; retrying");
                    std::thread::sleep(Duration::from_millis(100));
                }
                Err(e) => panic!("{e}"),
            }
        };
        let addr = server.local_addr().unwrap();
        runtime.spawn(server.run(std::future::pending()));
        Served {
            addr,
            runtime: Some(runtime),
        }
    }

    /// Serves one repository as `name`.
    pub fn one(addr: SocketAddr, name: &str, path: &Path) -> Served {
        Served::start(
            addr,
            vec![RepoConfig {
                name: name.into(),
                path: path.to_path_buf(),
            }],
        )
    }

    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    pub fn kill(mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_timeout(Duration::from_secs(5));
        }
    }
}

/// Builds repository `name` with `build` into `dir/built/name`: the path to serve and the
/// path the test reads locally at the same time, which are one (readers share a
/// repository).
pub fn built_and_local(dir: &Path, name: &str, build: impl FnOnce(&Path)) -> (PathBuf, PathBuf) {
    let built = dir.join("built").join(name);
    build(&built);
    (built.clone(), built)
}

/// Details read and decoded straight from a local copy of the repository.
pub struct Local<R: Domain> {
    pub repo: Repository,
    pub refiner: Arc<R>,
}

impl<R: Domain> DetailSource<R::Id> for Local<R> {
    fn details(&mut self, id: R::Id, _priority: f64) -> Availability<R::Id> {
        let info = self.refiner.info(id).expect("refinable");
        let blob = self.repo.get(&info.key).unwrap();
        Availability::Ready(blob.map(|b| Arc::new(self.refiner.decode(id, &b).unwrap())))
    }
}

/// Every cut half with its grid, sorted.
pub type Cut<I> = Vec<(I, Half, Vec<i32>)>;

pub fn cut_of<R: Domain>(dag: &Dag<R>) -> Cut<R::Id> {
    dag.cut()
        .into_iter()
        .map(|(id, h)| (id, h, dag.node(id).unwrap().grid.to_vec()))
        .collect()
}

/// The converged cut for `view` with every blob of the local copy at hand, in `world`
/// (the streamed session's: a planet's horizon culling depends on it).
pub fn reference_cut<R: Domain>(
    local: &Path,
    name: &str,
    view: &View,
    world: R::World,
) -> Cut<R::Id> {
    let repo = Repository::open(local).unwrap();
    let (refiner, _) = R::from_metadata(name, repo.metadata(), None).unwrap();
    let refiner = Arc::new(refiner);
    let mut dag = Dag::new(Arc::clone(&refiner));
    let mut source = Local { repo, refiner };
    let mut refinement = Refinement::default();
    let clock = SystemClock(Instant::now());
    for _ in 0..100 {
        let s = refinement
            .update(
                &mut dag,
                view,
                world,
                &mut source,
                &clock,
                Duration::from_secs(60),
            )
            .unwrap();
        if s.converged {
            return cut_of(&dag);
        }
    }
    panic!("the local refinement did not converge");
}

/// The 1920x1080, 60 degree, 1 px view of a flight pose, `up` from the world.
pub fn view_of(pose: &flight::Pose, world: &impl World) -> View {
    let eye = DVec3::from_array(pose.eye);
    View {
        eye,
        target: DVec3::from_array(pose.target),
        up: world.up(eye),
        fov_y_rad: 60f64.to_radians(),
        viewport_px: [1920, 1080],
        tolerance_px: 1.0,
    }
}

/// Runs frames for `view` until the session has converged (or panics after `limit`),
/// checking the cut after every frame.
pub fn converge<R: Domain>(session: &mut Session<R>, view: &View, start: Instant, limit: Duration) {
    let t0 = Instant::now();
    loop {
        let f = session
            .update(view, start.elapsed(), Duration::from_millis(8))
            .unwrap();
        let check = session.dag().check_cut();
        assert!(check.ok(), "{check:?}");
        if f.refine.converged && f.wanted == 0 {
            return;
        }
        assert!(t0.elapsed() < limit, "not converged: {f:?}");
        std::thread::sleep(Duration::from_millis(5));
    }
}

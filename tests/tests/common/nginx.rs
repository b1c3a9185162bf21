//! nginx for the end-to-end tests: found (or `SKIP`), configured under a temporary
//! directory, started in the foreground and stopped when dropped.

use std::net::{SocketAddr, TcpListener};
use std::os::unix::fs::MetadataExt as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use quincunx_testkit::skip::skip;

use super::{Response, try_get};

/// `/usr/sbin/nginx`, else `nginx` on `PATH`.
/// nginx (Debian's `/usr/sbin/nginx`, else on `PATH`), or `None` after printing
/// `SKIP <test>`; a failure instead with `REQUIRE_NGINX=1`, which CI sets.
pub fn find_nginx(test: &str) -> Option<PathBuf> {
    let debian = PathBuf::from("/usr/sbin/nginx");
    let found = if debian.is_file() {
        Some(debian)
    } else {
        std::env::var_os("PATH").and_then(|path| {
            std::env::split_paths(&path)
                .map(|dir| dir.join("nginx"))
                .find(|candidate| candidate.is_file())
        })
    };
    if found.is_none() {
        skip(
            test,
            "REQUIRE_NGINX",
            "nginx not installed (apt-get install nginx)",
        );
    }
    found
}

/// nginx running the shipped configuration, stopped when dropped.
pub struct Nginx {
    binary: PathBuf,
    dir: PathBuf,
    child: Child,
    /// Where it listens.
    pub addr: SocketAddr,
}

impl Nginx {
    /// Writes `dir/nginx.conf` (`snippet` inside a main context whose paths are all under
    /// `dir`) and starts nginx in the foreground, waiting until `ready` answers 200.
    pub fn run(binary: &Path, dir: &Path, addr: SocketAddr, snippet: &str, ready: &str) -> Nginx {
        let d = dir.display();
        // Workers of a root master run as `nobody` unless told otherwise, and could not
        // enter the 0700 temporary directory.
        let running_as_root = std::fs::metadata("/proc/self").is_ok_and(|m| m.uid() == 0);
        let user = if running_as_root { "user root;" } else { "" };
        std::fs::create_dir_all(dir.join("tmp")).unwrap();
        let conf = format!(
            "daemon off;\nmaster_process on;\nworker_processes 1;\n{user}\n\
             pid {d}/nginx.pid;\nerror_log {d}/error.log info;\n\
             events {{ worker_connections 256; }}\n\
             http {{\n\
             client_body_temp_path {d}/tmp/body;\nproxy_temp_path {d}/tmp/proxy;\n\
             fastcgi_temp_path {d}/tmp/fastcgi;\nuwsgi_temp_path {d}/tmp/uwsgi;\n\
             scgi_temp_path {d}/tmp/scgi;\n\
             {snippet}\n}}\n"
        );
        std::fs::write(dir.join("nginx.conf"), conf).unwrap();
        let child = Command::new(binary)
            .args(Self::location_args(dir))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let mut nginx = Nginx {
            binary: binary.to_path_buf(),
            dir: dir.to_path_buf(),
            child,
            addr,
        };
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Some(status) = nginx.child.try_wait().unwrap() {
                panic!("nginx exited with {status}:\n{}", nginx.error_log());
            }
            if let Ok(Response { status: 200, .. }) = try_get(addr, ready, &[]) {
                return nginx;
            }
            assert!(
                Instant::now() < deadline,
                "nginx did not answer on {addr} within 30 s:\n{}",
                nginx.error_log()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn location_args(dir: &Path) -> Vec<PathBuf> {
        vec![
            "-p".into(),
            dir.to_path_buf(),
            "-c".into(),
            dir.join("nginx.conf"),
            "-e".into(),
            dir.join("error.log"),
        ]
    }

    /// Lines of its access log (`dir/access.log`, where the configuration puts one) so far.
    pub fn access_log(&self) -> Vec<String> {
        std::fs::read_to_string(self.dir.join("access.log"))
            .unwrap_or_default()
            .lines()
            .map(str::to_string)
            .collect()
    }

    pub fn error_log(&self) -> String {
        std::fs::read_to_string(self.dir.join("error.log")).unwrap_or_default()
    }
}

impl Drop for Nginx {
    fn drop(&mut self) {
        // SIGTERM through the pid file: the master stops its workers (SIGKILL to the master
        // alone would leave the worker serving).
        let _ = Command::new(&self.binary)
            .args(Self::location_args(&self.dir))
            .args(["-s", "stop"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status();
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A loopback address nothing listens on right now.
pub fn free_port() -> SocketAddr {
    let probe = TcpListener::bind("127.0.0.1:0").unwrap();
    probe.local_addr().unwrap()
}

//! The network thread and its handle, [`Fetcher`].

use std::collections::{HashMap, HashSet};
use std::sync::mpsc as std_mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};

use super::bandwidth::{Bandwidth, Cap};
use super::cache::DecodedCache;
use super::schedule::{Backoff, Class, Scheduler};
use super::transport::{Completion, Driver, Request};
use super::{
    Decode, Decoded, FetchConfig, FetchError, FetchStats, Fetched, Key, Unpack, Weigh, lock,
};

/// Messages from the frame loop to the network thread.
enum Command {
    Wants {
        wants: Vec<(Key, f32)>,
        prefetch: Vec<(Key, f32)>,
        package_above: Option<f32>,
    },
    Stop,
}

/// State shared by the frame loop and the network thread.
struct Shared<T> {
    cache: Mutex<DecodedCache<T>>,
    stats: Mutex<FetchStats>,
}

type Results<T> = (Key, Fetched<T>);

/// The frame loop's handle on the network thread. Every method returns at once.
///
/// Dropping it stops the thread (requests in flight are abandoned).
///
/// ```no_run
/// use std::sync::Arc;
/// use std::time::Duration;
/// use quincunx_client::fetch::{FetchConfig, Fetched, Fetcher, Remote};
///
/// let (remote, _meta) = Remote::open("http://127.0.0.1:8080", "korea", Duration::from_secs(5))?;
/// let fetcher: Fetcher<Vec<u8>> =
///     Fetcher::spawn(FetchConfig::new(remote), Arc::new(|_key, bytes| Ok(bytes.to_vec())))?;
/// loop {
///     // Each frame: what the cut needs, most urgent first or not.
///     fetcher.submit(vec![([2048, 2048, 0], 1.0)]);
///     for (key, result) in fetcher.poll() {
///         match result {
///             Fetched::Data(blob) => { /* refine with it */ }
///             Fetched::Leaf => { /* stop refining here */ }
///             Fetched::Failed(e) => eprintln!("{key:?}: {e}"),
///         }
///     }
/// #   break;
/// }
/// # Ok::<(), quincunx_client::fetch::FetchError>(())
/// ```
pub struct Fetcher<T> {
    commands: UnboundedSender<Command>,
    results_tx: std_mpsc::Sender<Results<T>>,
    results: std_mpsc::Receiver<Results<T>>,
    shared: Arc<Shared<T>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl<T: Weigh + Send + Sync + 'static> Fetcher<T> {
    /// Starts the network thread (a tokio current-thread runtime) with `config`; `decode`
    /// runs on that thread for every non-empty blob.
    pub fn spawn(config: FetchConfig, decode: Decode<T>) -> Result<Fetcher<T>, FetchError> {
        let unpack: Unpack<T> = Arc::new(move |key, bytes, _packaged| {
            Ok(Decoded {
                value: decode(key, bytes)?,
                carried: Vec::new(),
            })
        });
        Fetcher::spawn_unpacking(config, unpack)
    }

    /// [`Fetcher::spawn`] for answers that carry other keys' values too: those are
    /// cached, dropped from the queue, and reported if wanted, as if fetched.
    pub fn spawn_unpacking(
        config: FetchConfig,
        decode: Unpack<T>,
    ) -> Result<Fetcher<T>, FetchError> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .enable_time()
            .build()
            .map_err(|e| FetchError::Thread(format!("runtime: {e}")))?;
        let (done_tx, done_rx) = unbounded_channel();
        let driver = {
            // The transport spawns its tasks onto this runtime; they run once the thread
            // drives it.
            let _entered = runtime.enter();
            Driver::new(&config, done_tx)?
        };
        let shared = Arc::new(Shared {
            cache: Mutex::new(DecodedCache::new(config.cache_bytes)),
            stats: Mutex::new(FetchStats::default()),
        });
        let (commands, commands_rx) = unbounded_channel();
        let (results_tx, results) = std_mpsc::channel();
        let now = Instant::now();
        let worker = Worker {
            cap: config.bandwidth_cap_bit_s.map(|c| Cap::new(c, now)),
            config,
            decode,
            shared: Arc::clone(&shared),
            results: results_tx.clone(),
            sched: Scheduler::new(),
            origin: now,
            bandwidth: Bandwidth::new(),
            charged: HashMap::new(),
            driver,
            stats: FetchStats::default(),
            package_above: None,
            packaged: HashSet::new(),
        };
        let thread = std::thread::Builder::new()
            .name("quincunx-fetch".into())
            .spawn(move || runtime.block_on(worker.run(commands_rx, done_rx)))
            .map_err(|e| FetchError::Thread(format!("spawn: {e}")))?;
        Ok(Fetcher {
            commands,
            results_tx,
            results,
            shared,
            thread: Some(thread),
        })
    }

    /// The frame's wanted keys with priorities (higher = more urgent). Replaces the
    /// previous frame's: keys not listed again are dropped from the queue. Keys cached or
    /// known to be leaves are answered at once (see [`Fetcher::poll`]).
    pub fn submit(&self, wants: Vec<(Key, f32)>) {
        self.submit_with_prefetch(wants, Vec::new());
    }

    /// Like [`Fetcher::submit`], plus `prefetch` keys (for the predicted camera), requested
    /// only when every wanted key is in flight and the bandwidth allows more. Prefetched
    /// blobs go to the cache; they are not reported by [`Fetcher::poll`].
    pub fn submit_with_prefetch(&self, wants: Vec<(Key, f32)>, prefetch: Vec<(Key, f32)>) {
        self.submit_packaged(wants, prefetch, None);
    }

    /// Like [`Fetcher::submit_with_prefetch`]; keys whose priority is at least
    /// `package_above` are asked for as packages (the answer carries small owned
    /// children's values too, [`Unpack`]), the others as bare blobs.
    pub fn submit_packaged(
        &self,
        wants: Vec<(Key, f32)>,
        prefetch: Vec<(Key, f32)>,
        package_above: Option<f32>,
    ) {
        let mut hits = 0u64;
        let (wants, prefetch) = {
            let mut cache = lock(&self.shared.cache);
            let wants: Vec<_> = wants
                .into_iter()
                .filter(|&(k, _)| {
                    let answer = if cache.is_leaf(k) {
                        Fetched::Leaf
                    } else if let Some(v) = cache.get(k) {
                        Fetched::Data(v)
                    } else {
                        return true;
                    };
                    hits += 1;
                    let _ = self.results_tx.send((k, answer));
                    false
                })
                .collect();
            let prefetch: Vec<_> = prefetch
                .into_iter()
                .filter(|&(k, _)| !cache.is_leaf(k) && !cache.contains(k))
                .collect();
            (wants, prefetch)
        };
        if hits > 0 {
            lock(&self.shared.stats).cache_hits += hits;
        }
        let _ = self.commands.send(Command::Wants {
            wants,
            prefetch,
            package_above,
        });
    }

    /// Results ready since the last call, in arrival order, each key at most once: a key
    /// submitted again after its answer was sent but before it was polled is answered a
    /// second time from the cache, and that repeat is dropped here.
    pub fn poll(&self) -> Vec<(Key, Fetched<T>)> {
        let mut seen = HashSet::new();
        self.results
            .try_iter()
            .filter(|(k, _)| seen.insert(*k))
            .collect()
    }

    /// A snapshot of the counters.
    pub fn stats(&self) -> FetchStats {
        lock(&self.shared.stats).clone()
    }

    /// The cached value of `key`, if any (marks it recently used).
    pub fn cached(&self, key: Key) -> Option<Arc<T>> {
        lock(&self.shared.cache).get(key)
    }

    /// Whether `key`'s value is cached (without marking it used).
    pub fn contains(&self, key: Key) -> bool {
        lock(&self.shared.cache).contains(key)
    }

    /// Whether `key` is known to be a leaf.
    pub fn is_leaf(&self, key: Key) -> bool {
        lock(&self.shared.cache).is_leaf(key)
    }

    /// Whether the network thread is still running.
    pub fn is_running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }
}

impl<T> Drop for Fetcher<T> {
    fn drop(&mut self) {
        let _ = self.commands.send(Command::Stop);
        if let Some(t) = self.thread.take()
            && t.join().is_err()
        {
            tracing::error!("the fetch thread panicked");
        }
    }
}

/// The network thread's state.
struct Worker<T> {
    config: FetchConfig,
    decode: Unpack<T>,
    shared: Arc<Shared<T>>,
    results: std_mpsc::Sender<Results<T>>,
    sched: Scheduler,
    /// The scheduler's time origin (it counts time as a `Duration` since this).
    origin: Instant,
    bandwidth: Bandwidth,
    cap: Option<Cap>,
    /// Bytes taken from the cap's bucket per request in flight, settled on completion.
    charged: HashMap<Key, f64>,
    driver: Driver,
    /// The thread's own counters, published to `shared.stats` after each event.
    stats: FetchStats,
    /// Priority from which keys are asked for as packages (latest submit).
    package_above: Option<f32>,
    /// Keys in flight asked for as packages.
    packaged: HashSet<Key>,
}

enum Event {
    Command(Option<Command>),
    Done(Option<Completion>),
    Wake,
}

/// Far enough to mean "no timer".
const NEVER: Duration = Duration::from_secs(3600);

impl<T: Weigh + Send + Sync + 'static> Worker<T> {
    /// `now` on the scheduler's clock.
    fn since(&self, now: Instant) -> Duration {
        now.saturating_duration_since(self.origin)
    }

    async fn run(
        mut self,
        mut commands: UnboundedReceiver<Command>,
        mut completions: UnboundedReceiver<Completion>,
    ) {
        loop {
            let now = Instant::now();
            let wake = [
                self.sched
                    .next_retry(self.since(now))
                    .map(|t| self.origin + t),
                self.cap.as_ref().and_then(Cap::ready_at),
            ]
            .into_iter()
            .flatten()
            .min();
            let sleep_until = tokio::time::Instant::from_std(wake.unwrap_or(now + NEVER));
            let event = tokio::select! {
                biased;
                c = commands.recv() => Event::Command(c),
                d = completions.recv() => Event::Done(d),
                () = tokio::time::sleep_until(sleep_until), if wake.is_some() => Event::Wake,
            };
            match event {
                Event::Command(None | Some(Command::Stop)) | Event::Done(None) => break,
                Event::Command(Some(Command::Wants {
                    wants,
                    prefetch,
                    package_above,
                })) => {
                    // Only the latest frame's wants matter.
                    let (mut wants, mut prefetch) = (wants, prefetch);
                    self.package_above = package_above;
                    while let Ok(next) = commands.try_recv() {
                        match next {
                            Command::Wants {
                                wants: w,
                                prefetch: p,
                                package_above: a,
                            } => (wants, prefetch, self.package_above) = (w, p, a),
                            Command::Stop => return,
                        }
                    }
                    let now = Instant::now();
                    self.bandwidth.on_submit(now);
                    self.sched.set_wants(&wants, &prefetch, self.since(now));
                }
                Event::Done(Some(first)) => {
                    self.complete(first);
                    while let Ok(more) = completions.try_recv() {
                        self.complete(more);
                    }
                }
                Event::Wake => {}
            }
            self.issue(Instant::now());
            self.publish();
        }
        tracing::debug!("fetch thread stops");
    }

    /// Requests the most urgent keys the window, the cap and the transport allow.
    fn issue(&mut self, now: Instant) {
        self.bandwidth.advance(now, self.sched.in_flight());
        let window = self.bandwidth.window(
            self.config.initial_in_flight,
            self.config.max_in_flight,
            self.config.bandwidth_cap_bit_s,
        );
        self.stats.window = window;
        let room = window
            .saturating_sub(self.sched.in_flight())
            .min(self.driver.free_slots());
        if room == 0 {
            return;
        }
        let keys = {
            let t = self.since(now);
            let cache = lock(&self.shared.cache);
            self.sched
                .next(t, room, |k| cache.is_leaf(k) || cache.contains(k))
        };
        let expected = self.bandwidth.mean_bytes().max(1.0);
        for key in keys {
            if let Some(cap) = &mut self.cap {
                if !cap.try_take(now, expected) {
                    break;
                }
                self.charged.insert(key, expected);
            }
            let packaged = self
                .package_above
                .is_some_and(|t| self.sched.priority(key).is_some_and(|p| p >= t));
            let path = if packaged {
                self.config.remote.package_path(key)
            } else {
                self.config.remote.blob_path(key)
            };
            if !self.driver.send(Request { key, path }) {
                if let (Some(cap), Some(charged)) = (&mut self.cap, self.charged.remove(&key)) {
                    cap.correct(charged, 0.0);
                }
                break;
            }
            tracing::trace!(?key, packaged, "request");
            if packaged {
                self.packaged.insert(key);
            }
            self.sched.issued(key, self.since(now));
            self.stats.requests += 1;
        }
    }

    fn deliver(&self, key: Key, result: Fetched<T>) {
        let _ = self.results.send((key, result));
    }

    /// Handles the end of one request.
    fn complete(&mut self, done: Completion) {
        let now = Instant::now();
        self.driver.finished(done.slot);
        let in_flight_before = self.sched.in_flight();
        let packaged = self.packaged.remove(&done.key);
        let Some((latency, issued_as)) = self.sched.finished(done.key, self.since(now)) else {
            return;
        };
        let key = done.key;
        if let (Some(cap), Some(charged)) = (&mut self.cap, self.charged.remove(&key)) {
            let actual = match &done.result {
                Ok((_, body)) => body.len() as f64,
                Err(_) => 0.0,
            };
            cap.correct(charged, actual);
        }
        // Report to the frame loop what it asked for (not prefetches it no longer wants).
        let report = issued_as == Class::Want || self.sched.class(key) == Some(Class::Want);
        let answer = match done.result {
            Ok((200, body)) => Ok(body),
            // A static export has no file for a leaf.
            Ok((404, _)) if self.config.remote.static_export => Ok(Bytes::new()),
            Ok((status, _)) => Err(FetchError::Status(status)),
            Err(e) => Err(e),
        };
        match answer {
            Ok(body) => {
                self.answered(key, body, packaged, latency, report);
                self.bandwidth.advance(now, in_flight_before);
            }
            Err(error) => {
                self.bandwidth.advance(now, in_flight_before);
                self.failed(key, error, now, report);
            }
        }
    }

    /// A 200 answer: a leaf, or a blob to decode and cache.
    fn answered(&mut self, key: Key, body: Bytes, packaged: bool, latency: Duration, report: bool) {
        let len = body.len();
        self.stats.responses += 1;
        self.stats.bytes_fetched += len as u64;
        self.bandwidth.on_answer(len, Some(latency));
        self.sched.succeeded(key);
        self.sched.unwant(key);
        if body.is_empty() {
            self.stats.leaves += 1;
            lock(&self.shared.cache).mark_leaf(key);
            if report {
                self.deliver(key, Fetched::Leaf);
            }
            return;
        }
        match (self.decode)(key, body, packaged) {
            Ok(Decoded { value, carried }) => {
                // Carried keys first: once the asked key is cached, so is what it carried.
                for (k, v) in carried {
                    self.stats.carried += 1;
                    let wanted = self.sched.class(k) == Some(Class::Want);
                    self.sched.unwant(k);
                    let v = Arc::new(v);
                    lock(&self.shared.cache).insert(k, Arc::clone(&v));
                    if wanted {
                        self.deliver(k, Fetched::Data(v));
                    }
                }
                let value = Arc::new(value);
                lock(&self.shared.cache).insert(key, Arc::clone(&value));
                if report {
                    self.deliver(key, Fetched::Data(value));
                }
            }
            Err(reason) => {
                let now = Instant::now();
                self.failed(key, FetchError::Decode(reason), now, report);
            }
        }
    }

    /// A failed attempt: retried after a backoff if transient, reported if permanent or
    /// after `max_attempts` failures in a row.
    fn failed(&mut self, key: Key, error: FetchError, now: Instant, report: bool) {
        self.stats.errors.count(&error);
        let backoff = Backoff {
            base: self.config.retry_backoff,
            max: self.config.max_backoff,
        };
        let give_up = if error.is_transient() {
            let failures = self.sched.failed(key, self.since(now), backoff);
            tracing::debug!(?key, failures, %error, "transient failure");
            failures >= self.config.max_attempts
        } else {
            tracing::debug!(?key, %error, "permanent failure");
            self.sched.hold(key, self.since(now), backoff.max);
            true
        };
        if give_up {
            self.sched.unwant(key);
            if report {
                self.deliver(key, Fetched::Failed(error));
            }
        }
    }

    fn publish(&mut self) {
        self.stats.in_flight = self.sched.in_flight();
        self.stats.queued = self.sched.queued();
        self.stats.bandwidth_bit_s = self.bandwidth.rate_bit_s();
        self.stats.rtt = self.bandwidth.rtt();
        self.stats.latency = self.bandwidth.latency();
        self.stats.mean_blob_bytes = self.bandwidth.mean_bytes();
        let mut shared = lock(&self.shared.stats);
        let cache_hits = shared.cache_hits;
        *shared = self.stats.clone();
        shared.cache_hits = cache_hits;
    }
}

//! The network thread and its handle, [`Fetcher`].

use std::collections::HashSet;
use std::sync::mpsc as std_mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};

use std::collections::VecDeque;

use quincunx_client_core::fetch::cache::DecodedCache;
use quincunx_client_core::fetch::planner::{Answer, Planner};
use quincunx_client_core::fetch::ranges::{RangeReader, RangeRequest, Step};

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
        let mut planner = Planner::new(config.planner(), Duration::ZERO);
        let ranges = config.remote.pack.as_ref().map(|pack| {
            // Opening the file is part of what the session fetched.
            planner.spent(pack.open_requests, pack.open_bytes);
            Ranges {
                reader: RangeReader::new(Arc::clone(&pack.index), config.ranges),
                pack: Arc::clone(pack),
                queued: VecDeque::new(),
            }
        });
        let worker = Worker {
            ranges,
            config,
            decode,
            shared: Arc::clone(&shared),
            results: results_tx.clone(),
            planner,
            origin: Instant::now(),
            driver,
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
        let (held, wants, prefetch) = lock(&self.shared.cache).answer_held(wants, prefetch);
        if !held.is_empty() {
            lock(&self.shared.stats).cache_hits += held.len() as u64;
        }
        for (k, v) in held {
            let answer = v.map_or(Fetched::Leaf, Fetched::Data);
            let _ = self.results_tx.send((k, answer));
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

/// Range reads of a repository file: the core's [`RangeReader`] and the requests the
/// transport had no room for yet.
struct Ranges {
    reader: RangeReader,
    pack: Arc<super::remote::PackFile>,
    queued: VecDeque<RangeRequest>,
}

/// The network thread: the transports and the clock around the core's [`Planner`].
struct Worker<T> {
    /// Reading a repository file with range requests (else blob URLs).
    ranges: Option<Ranges>,
    config: FetchConfig,
    decode: Unpack<T>,
    shared: Arc<Shared<T>>,
    results: std_mpsc::Sender<Results<T>>,
    /// Every decision: what to request, how many, what an answer means.
    planner: Planner,
    /// The planner's time origin (it counts time as a `Duration` since this).
    origin: Instant,
    driver: Driver,
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
            let wake = self
                .planner
                .wake_at(self.since(now))
                .map(|t| self.origin + t);
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
                    let (mut wants, mut prefetch, mut package_above) =
                        (wants, prefetch, package_above);
                    while let Ok(next) = commands.try_recv() {
                        match next {
                            Command::Wants {
                                wants: w,
                                prefetch: p,
                                package_above: a,
                            } => (wants, prefetch, package_above) = (w, p, a),
                            Command::Stop => return,
                        }
                    }
                    let now = self.since(Instant::now());
                    self.planner.submit(&wants, &prefetch, package_above, now);
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
        if self.ranges.is_some() {
            self.issue_ranges(now);
            return;
        }
        let now = self.since(now);
        let planned = {
            let cache = lock(&self.shared.cache);
            self.planner.plan(now, self.driver.free_slots(), |k| {
                cache.is_leaf(k) || cache.contains(k)
            })
        };
        let mut planned = planned.into_iter();
        while let Some(request) = planned.next() {
            let path = if request.packaged {
                self.config.remote.package_path(request.key)
            } else {
                self.config.remote.blob_path(request.key)
            };
            if !self.driver.send(Request::get(request.key, path)) {
                self.planner.unsent(request.key);
                for rest in planned {
                    self.planner.unsent(rest.key);
                }
                break;
            }
            tracing::trace!(key = ?request.key, packaged = request.packaged, "request");
            self.planner.sent(request, now);
        }
    }

    fn deliver(&self, key: Key, result: Fetched<T>) {
        let _ = self.results.send((key, result));
    }

    /// Range reads: plans keys while nothing waits for the transport, turns them into
    /// range requests (leaves need none), and sends what the transport takes.
    fn issue_ranges(&mut self, now: Instant) {
        let now = self.since(now);
        let Some(ranges) = &self.ranges else {
            return;
        };
        if ranges.queued.is_empty() {
            // A request carries many keys: plan beyond the transport's free slots.
            let room = self.driver.free_slots().saturating_mul(64);
            let planned = {
                let cache = lock(&self.shared.cache);
                self.planner
                    .plan(now, room, |k| cache.is_leaf(k) || cache.contains(k))
            };
            if !planned.is_empty() {
                let keys: Vec<(Key, bool)> = planned.iter().map(|p| (p.key, p.packaged)).collect();
                for p in planned {
                    self.planner.sent_uncounted(p, now);
                }
                let step = match &mut self.ranges {
                    Some(r) => r.reader.plan(&keys),
                    None => return,
                };
                self.apply(step, now);
            }
        }
        self.send_ranges();
    }

    /// Sends queued range requests while the transport has room.
    fn send_ranges(&mut self) {
        let Some(ranges) = &mut self.ranges else {
            return;
        };
        while let Some(r) = ranges.queued.front() {
            let request = Request {
                key: [0; 3],
                tag: r.tag,
                path: ranges.pack.path.clone(),
                headers: ranges.pack.headers(r),
            };
            if !self.driver.send(request) {
                break;
            }
            tracing::trace!(tag = r.tag, range = ?r.range, "range request");
            ranges.queued.pop_front();
            self.planner.spent(1, 0);
        }
    }

    /// What a range reader's step asks for: leaves and blobs (or failures) to hand on,
    /// requests to queue, bytes spent besides blobs.
    fn apply(&mut self, step: Step, now: Duration) {
        let Step {
            leaves,
            blobs,
            requests,
            overhead_bytes,
        } = step;
        self.planner.spent(0, overhead_bytes);
        if let Some(r) = &mut self.ranges {
            r.queued.extend(requests);
        }
        for key in leaves {
            if let Answer::Leaf { report } = self.planner.leaf_known(key, now) {
                lock(&self.shared.cache).mark_leaf(key);
                if report {
                    self.deliver(key, Fetched::Leaf);
                }
            }
        }
        for (key, blob) in blobs {
            self.answer(key, blob.map(|b| (200, b)), now);
        }
    }

    /// Handles the end of one request.
    fn complete(&mut self, done: Completion) {
        let now = self.since(Instant::now());
        self.driver.finished(done.slot);
        if done.tag != 0 {
            let Some(ranges) = &mut self.ranges else {
                return;
            };
            let Some(range) = ranges.reader.range_of(done.tag) else {
                return;
            };
            let meta = done.range.unwrap_or_default();
            let body = done.result.and_then(|(status, body)| {
                ranges.pack.check_answer(
                    range,
                    status,
                    body,
                    meta.content_range,
                    meta.etag.as_deref(),
                )
            });
            if let Err(e) = &body {
                tracing::debug!(tag = done.tag, %e, "range request failed");
            }
            let step = ranges.reader.answered(done.tag, body);
            self.apply(step, now);
            self.send_ranges();
            return;
        }
        self.answer(done.key, done.result, now);
    }

    /// The answer to `key`: a status and body, or why there is none.
    fn answer(&mut self, key: Key, result: Result<(u16, Bytes), FetchError>, now: Duration) {
        match self.planner.complete(key, result, now) {
            Answer::Stale | Answer::Failed(None) => {}
            Answer::Failed(Some(error)) => self.deliver(key, Fetched::Failed(error)),
            Answer::Leaf { report } => {
                lock(&self.shared.cache).mark_leaf(key);
                if report {
                    self.deliver(key, Fetched::Leaf);
                }
            }
            Answer::Body {
                body,
                packaged,
                report,
            } => self.decoded(key, body, packaged, report),
        }
    }

    /// A body to decode and cache, with whatever it carried.
    fn decoded(&mut self, key: Key, body: Bytes, packaged: bool, report: bool) {
        match (self.decode)(key, body, packaged) {
            Ok(Decoded { value, carried }) => {
                let results = &self.results;
                self.planner.store_decoded(
                    &mut lock(&self.shared.cache),
                    key,
                    value,
                    carried,
                    report,
                    |k, v| {
                        let _ = results.send((k, Fetched::Data(v)));
                    },
                );
            }
            Err(reason) => {
                let now = self.since(Instant::now());
                if let Some(error) = self.planner.decode_failed(key, reason, now, report) {
                    self.deliver(key, Fetched::Failed(error));
                }
            }
        }
    }

    fn publish(&mut self) {
        let stats = self.planner.stats().clone();
        let mut shared = lock(&self.shared.stats);
        let cache_hits = shared.cache_hits;
        *shared = stats;
        shared.cache_hits = cache_hits;
    }
}

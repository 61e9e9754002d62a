//! Every decoder of network messages and files, fed a million or more
//! mutated inputs each (issue 30, item 2): real messages and files captured
//! from runs (`tests/fuzz_corpus/<decoder>/`, see [`capture_corpus`]) with bits
//! flipped, bytes set, cut short, extended with random bytes, varint length
//! fields forced to their extremes (bincode's markers 251–255 followed by
//! u16/u32/u64/u128 maxima, 2^62, runs of 0xFF) and replaced by random bytes.
//! No input may panic (each decode runs under `catch_unwind`, a panicking
//! input is reported in hex), abort (the process would die), or make a
//! single allocation larger than 32 × its length + 2 MiB (the bound of
//! `formation_record::bounded::decode_bounded`): a counting global allocator
//! measures every allocation of the decoding thread. Each decoder takes
//! exactly 1,000,000 inputs (`FUZZ_INPUTS`, in batches of 1,000) from a
//! generator seeded per decoder, the same inputs on every machine however
//! slow: no clock decides how many (a 120 s bound did, and the one-core
//! acceptance run of issue 64 failed on it: 953,004 checkpoint inputs in
//! 120 s). The slowest, the checkpoint's and hearing.bin's, take some 45 s
//! on a loaded 2-core machine. Two threads (`FUZZ_THREADS`) take the
//! decoders in turn. The attacks the issue names are refused
//! ([`the_issues_attack_inputs_are_refused`]); large inputs made of empty
//! strings or lists, which mutation of the small corpus cannot reach, are
//! measured apart ([`large_inputs_of_empty_elements`]: up to 48 × their
//! length in one allocation, more than the 32 × above). `cargo fuzz`
//! targets for nightly are in `fuzz/` (docs/security.md, "Fuzzing the
//! decoders").
//!
//! Run with `cargo test --test it fuzz_decoders:: -- --nocapture` to see, per
//! decoder, the inputs, how many decoded and how many were refused, the
//! largest allocation and the time taken.

use crate::common;

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use formation_net::clock_sync::TimeReply;
use formation_protocol::barrier::{Ready, Start};
use formation_protocol::telemetry::{Ack, Telemetry};
use formation_record::hearing::{HearingError, HearingRecord};

// ---------------------------------------------------------------------------
// A counting allocator: per thread (only a thread that is measuring counts),
// the largest single request and the bytes live, and their peak.

struct Counting;

thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    /// Bytes allocated and not yet freed while counting.
    static LIVE: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
    /// The largest single request (an allocation or a reallocation's new size).
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

fn counting() -> bool {
    COUNTING.try_with(Cell::get).unwrap_or(false)
}

fn grew(size: usize) {
    let _ = LARGEST.try_with(|l| l.set(l.get().max(size)));
    let _ = LIVE.try_with(|l| {
        let live = l.get() + size;
        l.set(live);
        let _ = PEAK.try_with(|p| p.set(p.get().max(live)));
    });
}

fn shrank(size: usize) {
    let _ = LIVE.try_with(|l| l.set(l.get().saturating_sub(size)));
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if counting() {
            grew(layout.size());
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if counting() {
            grew(layout.size());
        }
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if counting() {
            shrank(layout.size());
        }
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if counting() {
            // The old and the new block may both be live while it moves.
            grew(new_size);
            shrank(layout.size());
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// What one call allocated: its largest single request and its peak of live bytes.
#[derive(Clone, Copy, Debug, Default)]
struct Allocated {
    largest: usize,
    peak: usize,
}

/// Runs `f` with this thread's allocations counted (what `f` returns is
/// dropped inside, so its memory counts as well).
fn measure<R>(f: impl FnOnce() -> R) -> Allocated {
    LIVE.set(0);
    PEAK.set(0);
    LARGEST.set(0);
    COUNTING.set(true);
    drop(f());
    COUNTING.set(false);
    Allocated { largest: LARGEST.get(), peak: PEAK.get() }
}

/// The allocation bound of `decode_bounded` for an input of `len` bytes.
fn bound(len: usize) -> usize {
    2 * formation_record::bounded::ALLOCATION_FACTOR * len + (2 << 20)
}

// ---------------------------------------------------------------------------
// A seeded xorshift64* and the mutator.

struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Rng(seed.max(1))
    }
    fn next(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    /// Uniform in 0..n (n > 0).
    fn below(&mut self, n: usize) -> usize {
        (((self.next() >> 32) * n as u64) >> 32) as usize
    }
    fn byte(&mut self) -> u8 {
        (self.next() >> 56) as u8
    }
    fn chance(&mut self, one_in: usize) -> bool {
        self.below(one_in) == 0
    }
}

/// Bincode varints at their extremes: the markers 251 (u16), 252 (u32), 253
/// (u64), 254 (u128) followed by maxima or powers of two, 255 (invalid), and
/// single bytes at the marker boundary.
fn extreme_varint(rng: &mut Rng) -> Vec<u8> {
    let mut v = Vec::with_capacity(17);
    match rng.below(12) {
        0 => v.extend([251, 0xFF, 0xFF]),
        1 => v.extend([252, 0xFF, 0xFF, 0xFF, 0xFF]),
        2 => {
            v.push(253);
            v.extend(u64::MAX.to_le_bytes());
        }
        3 => {
            v.push(254);
            v.extend(u128::MAX.to_le_bytes());
        }
        4 => {
            v.push(253);
            v.extend((1u64 << 62).to_le_bytes());
        }
        5 => {
            v.push(252);
            v.extend((1u32 << 31).to_le_bytes());
        }
        6 => {
            v.push(253);
            v.extend((1u64 << (32 + rng.below(32))).to_le_bytes());
        }
        7 => {
            v.push(254);
            v.extend((1u128 << (64 + rng.below(64))).to_le_bytes());
        }
        8 => v.push(255),
        9 => v.push(250 + rng.below(6) as u8),
        10 => {
            // A plausible but too large length: up to 2^24.
            v.push(252);
            v.extend((rng.below(1 << 24) as u32).to_le_bytes());
        }
        _ => v.push(rng.byte()),
    }
    v
}

fn interesting_byte(rng: &mut Rng) -> u8 {
    const B: [u8; 12] = [0, 1, 0x7F, 0x80, 0xFA, 0xFB, 0xFC, 0xFD, 0xFE, 0xFF, b'"', b'\\'];
    if rng.chance(2) {
        B[rng.below(B.len())]
    } else {
        rng.byte()
    }
}

/// JSON fragments for the JSON decoders.
fn json_token(rng: &mut Rng) -> Vec<u8> {
    const T: [&str; 22] = [
        "\"",
        "[",
        "]",
        "{",
        "}",
        ",",
        ":",
        "null",
        "true",
        "-",
        "1e999999",
        "18446744073709551616",
        "-9223372036854775809",
        "340282366920938463463374607431768211456",
        "0.0000000000000000000000000001e-400",
        "\\u0000",
        "\\ud800",
        "\\uDFFF\\uD800",
        "\"\\",
        "NaN",
        "\u{FEFF}",
        "\"node\":\"router\"",
    ];
    match rng.below(10) {
        // Deep nesting (serde_json refuses past 128 levels).
        0 => {
            let depth = 1 + rng.below(4096);
            let open = if rng.chance(2) { b'[' } else { b'{' };
            vec![open; depth]
        }
        // A long string or number.
        1 => {
            let fill = if rng.chance(2) { b'9' } else { b'a' };
            vec![fill; 1 + rng.below(4096)]
        }
        _ => T[rng.below(T.len())].as_bytes().to_vec(),
    }
}

fn offset(rng: &mut Rng, len: usize) -> usize {
    if len == 0 {
        0
    } else {
        rng.below(len + 1)
    }
}

/// One mutated input from `seeds` into `out`; which seed it began from.
fn mutate(rng: &mut Rng, seeds: &[Vec<u8>], json: bool, out: &mut Vec<u8>) -> usize {
    out.clear();
    let from = rng.below(seeds.len());
    let seed = &seeds[from];
    if rng.chance(32) {
        // Random bytes, some as long as the seed.
        let n = rng.below(2 * seed.len() + 16);
        out.extend((0..n).map(|_| rng.byte()));
        return from;
    }
    out.extend_from_slice(seed);
    let rounds = 1 + rng.below(4) * rng.below(3);
    for _ in 0..rounds {
        let len = out.len();
        match rng.below(if json { 13 } else { 12 }) {
            // Bit flips.
            0 | 1 if len > 0 => {
                for _ in 0..1 + rng.below(4) {
                    let bit = rng.below(8 * len);
                    out[bit / 8] ^= 1 << (bit % 8);
                }
            }
            // A byte set.
            2 if len > 0 => {
                let at = rng.below(len);
                out[at] = interesting_byte(rng);
            }
            // Cut short.
            3 => {
                let at = offset(rng, len);
                out.truncate(at);
            }
            // Extended with random bytes.
            4 => {
                let n = 1 + rng.below(64);
                out.extend((0..n).map(|_| rng.byte()));
            }
            // A varint at an extreme, inserted or written over.
            5 | 6 => {
                let v = extreme_varint(rng);
                let at = offset(rng, len);
                if rng.chance(2) {
                    out.splice(at..at, v);
                } else {
                    let end = (at + v.len()).min(len);
                    out.splice(at..end, v);
                }
            }
            // A run of 0xFF or 0x00.
            7 if len > 0 => {
                let at = rng.below(len);
                let end = (at + 1 + rng.below(16)).min(len);
                let fill = if rng.chance(2) { 0xFF } else { 0 };
                out[at..end].fill(fill);
            }
            // A little-endian integer at an extreme, written over.
            8 if len > 0 => {
                const X: [u64; 6] = [0, u64::MAX, 1 << 62, 1 << 31, u32::MAX as u64, i64::MAX as u64];
                let bytes = X[rng.below(X.len())].to_le_bytes();
                let width = [2, 4, 8][rng.below(3)];
                let at = rng.below(len);
                let end = (at + width).min(len);
                out[at..end].copy_from_slice(&bytes[..end - at]);
            }
            // A range deleted.
            9 if len > 0 => {
                let at = rng.below(len);
                let end = (at + 1 + rng.below(32)).min(len);
                out.drain(at..end);
            }
            // A range repeated, or spliced in from another seed.
            10 | 11 => {
                let other = if rng.chance(2) { out.clone() } else { seeds[rng.below(seeds.len())].clone() };
                if !other.is_empty() {
                    let a = rng.below(other.len());
                    let b = (a + 1 + rng.below(64)).min(other.len());
                    let at = offset(rng, len);
                    out.splice(at..at, other[a..b].iter().copied());
                }
            }
            // JSON tokens.
            _ if json => {
                let t = json_token(rng);
                let at = offset(rng, len);
                if rng.chance(2) {
                    out.splice(at..at, t);
                } else {
                    let end = (at + t.len()).min(len);
                    out.splice(at..end, t);
                }
            }
            _ => {}
        }
    }
    from
}

// ---------------------------------------------------------------------------
// The decoders.

/// CRC-32 (IEEE, as crc32fast): a mutated hearing record gets a matching
/// checksum half of the time, so that what decodes is also checked past it.
fn crc32(bytes: &[u8]) -> u32 {
    static TABLE: std::sync::OnceLock<[u32; 256]> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        let mut t = [0u32; 256];
        for (i, e) in t.iter_mut().enumerate() {
            let mut c = i as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 { (c >> 1) ^ 0xEDB8_8320 } else { c >> 1 };
            }
            *e = c;
        }
        t
    });
    !bytes.iter().fold(!0u32, |crc, &b| table[((crc ^ u32::from(b)) & 0xFF) as usize] ^ (crc >> 8))
}

/// The checkpoint files' folder: tmpfs where there is one (every input is
/// written to a file and read by `checkpoint::read`).
fn checkpoint_dir() -> tempfile::TempDir {
    let shm = Path::new("/dev/shm");
    if shm.is_dir() {
        if let Ok(d) = tempfile::Builder::new().prefix("fuzz-checkpoint").tempdir_in(shm) {
            return d;
        }
    }
    tempfile::tempdir().expect("tempdir")
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    Estimate,
    Telemetry,
    Ack,
    Ready,
    Start,
    TimeReply,
    Hearing,
    Denials,
    Checkpoint,
}

const KINDS: [Kind; 9] = [
    Kind::Estimate,
    Kind::Telemetry,
    Kind::Ack,
    Kind::Ready,
    Kind::Start,
    Kind::TimeReply,
    Kind::Hearing,
    Kind::Denials,
    Kind::Checkpoint,
];

impl Kind {
    /// The corpus folder and the name printed.
    fn name(self) -> &'static str {
        match self {
            Kind::Estimate => "estimate",
            Kind::Telemetry => "telemetry",
            Kind::Ack => "ack",
            Kind::Ready => "ready",
            Kind::Start => "start",
            Kind::TimeReply => "timereply",
            Kind::Hearing => "hearing",
            Kind::Denials => "denials",
            Kind::Checkpoint => "checkpoint",
        }
    }
    fn decoder(self) -> &'static str {
        match self {
            Kind::Estimate => "formation_protocol::wire::decode",
            Kind::Telemetry => "codec::decode::<Telemetry>",
            Kind::Ack => "codec::decode::<Ack>",
            Kind::Ready => "codec::decode::<Ready>",
            Kind::Start => "codec::decode::<Start>",
            Kind::TimeReply => "codec::decode::<TimeReply>",
            Kind::Hearing => "HearingRecord::decode",
            Kind::Denials => "denials::Table::file",
            Kind::Checkpoint => "checkpoint::read",
        }
    }
    fn json(self) -> bool {
        matches!(self, Kind::Denials | Kind::Checkpoint)
    }
}

/// What a decoder is given besides the bytes: the JSON decoders check who
/// sent a report (the key it came on) and which run a checkpoint belongs
/// to; a mutated input is judged as its seed's.
struct Context {
    /// Per seed: the denial report's node, the checkpoint's fingerprint and epoch.
    who: Vec<(String, u64, u64)>,
    /// Where checkpoint inputs are written.
    dir: Option<tempfile::TempDir>,
}

impl Context {
    fn new(kind: Kind, seeds: &[Vec<u8>]) -> Self {
        let who = seeds
            .iter()
            .map(|s| {
                let v: serde_json::Value =
                    if kind.json() { serde_json::from_slice(s).expect("a JSON seed") } else { serde_json::Value::Null };
                let n = |key: &str| v[key].as_u64().unwrap_or(0);
                (v["node"].as_str().unwrap_or("router").to_string(), n("fingerprint"), n("epoch_unix_ns"))
            })
            .collect();
        Context { who, dir: (kind == Kind::Checkpoint).then(checkpoint_dir) }
    }

    /// No seeds: a report is `router`'s, a checkpoint of fingerprint and epoch 0.
    fn plain() -> Self {
        Context { who: vec![("router".into(), 0, 0)], dir: None }
    }

    fn checkpoint_path(&self) -> PathBuf {
        self.dir.as_ref().expect("a checkpoint folder").path().join("fuzz-follower-1.json")
    }
}

/// Runs `kind`'s decoder on `bytes`: whether it decoded.
fn decode(kind: Kind, bytes: &[u8], cx: &Context, seed: usize) -> bool {
    let (node, fingerprint, epoch) = &cx.who[seed];
    use formation_protocol::codec;
    match kind {
        Kind::Estimate => formation_protocol::wire::decode(bytes).is_ok(),
        Kind::Telemetry => codec::decode::<Telemetry>(bytes).is_some(),
        Kind::Ack => codec::decode::<Ack>(bytes).is_some(),
        Kind::Ready => codec::decode::<Ready>(bytes).is_some(),
        Kind::Start => codec::decode::<Start>(bytes).is_some(),
        Kind::TimeReply => codec::decode::<TimeReply>(bytes).is_some(),
        Kind::Hearing => HearingRecord::decode(bytes, "fuzz/hearing.bin").is_ok(),
        Kind::Denials => formation_protocol::denied::Table::default().file(node, bytes),
        Kind::Checkpoint => formation_net::checkpoint::read(&cx.checkpoint_path(), *fingerprint, *epoch).is_ok(),
    }
}

fn corpus_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_corpus")
}

fn corpus(kind: Kind) -> Vec<Vec<u8>> {
    let dir = corpus_dir().join(kind.name());
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e} (capture it: see capture_corpus)", dir.display()))
        .map(|e| e.expect("corpus entry").path())
        .collect();
    files.sort();
    let seeds: Vec<Vec<u8>> = files.iter().map(|f| std::fs::read(f).expect("corpus file")).collect();
    assert!(!seeds.is_empty(), "{}: no corpus", dir.display());
    seeds
}

// ---------------------------------------------------------------------------
// The loop.

#[derive(Debug, Default)]
struct Tally {
    inputs: u64,
    decoded: u64,
    refused: u64,
    /// Inputs that panicked, in hex (the first few).
    panics: Vec<String>,
    panicked: u64,
    /// The largest single allocation, and the length of the input that made it.
    largest: (usize, usize),
    /// The largest peak of live bytes, and its input's length.
    peak: (usize, usize),
    /// The largest single allocation over the input's length (inputs of 64 bytes or more).
    ratio: f64,
    /// The largest single allocation over its input's bound (32 x length + 2 MiB).
    bound_use: f64,
    /// Inputs whose largest allocation exceeded the bound (the first few, in hex).
    over_bound: Vec<String>,
    elapsed: Duration,
    seeds: usize,
    seeds_decoded: usize,
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// One decoder run on one input: counted into `t`.
fn one(kind: Kind, input: &[u8], cx: &Context, seed: usize, t: &mut Tally) {
    if kind == Kind::Checkpoint {
        std::fs::write(cx.checkpoint_path(), input).expect("writing a checkpoint input");
    }
    let mut ok = None;
    let a = measure(|| ok = Some(std::panic::catch_unwind(AssertUnwindSafe(|| decode(kind, input, cx, seed)))));
    t.inputs += 1;
    match ok {
        Some(Ok(true)) => t.decoded += 1,
        Some(Ok(false)) => t.refused += 1,
        _ => {
            t.panicked += 1;
            if t.panics.len() < 5 {
                t.panics.push(hex(input));
            }
        }
    }
    if a.largest > t.largest.0 {
        t.largest = (a.largest, input.len());
    }
    if a.peak > t.peak.0 {
        t.peak = (a.peak, input.len());
    }
    if input.len() >= 64 {
        t.ratio = t.ratio.max(a.largest as f64 / input.len() as f64);
    }
    t.bound_use = t.bound_use.max(a.largest as f64 / bound(input.len()) as f64);
    if a.largest > bound(input.len()) && t.over_bound.len() < 5 {
        t.over_bound.push(format!("{} bytes allocated for {}", a.largest, hex(input)));
    }
}

fn fuzz(kind: Kind, target: u64) -> Tally {
    let seeds = corpus(kind);
    let cx = Context::new(kind, &seeds);
    let mut t = Tally { seeds: seeds.len(), ..Tally::default() };
    if kind == Kind::Hearing {
        for s in &seeds {
            let n = s.len() - 4;
            assert_eq!(crc32(&s[..n]).to_le_bytes(), s[n..], "this test's CRC-32 is not the record's");
        }
    }
    // The seeds themselves: real messages decode.
    for (i, s) in seeds.iter().enumerate() {
        one(kind, s, &cx, i, &mut t);
    }
    t.seeds_decoded = t.decoded as usize;
    let mut rng = Rng::new(0x5eed_0000 + kind as u64);
    let mut input = Vec::new();
    let began = Instant::now();
    while t.inputs < target {
        for _ in 0..1000 {
            let seed = mutate(&mut rng, &seeds, kind.json(), &mut input);
            if kind == Kind::Hearing && input.len() >= 4 && rng.chance(2) {
                let n = input.len() - 4;
                let crc = crc32(&input[..n]).to_le_bytes();
                input[n..].copy_from_slice(&crc);
            }
            one(kind, &input, &cx, seed, &mut t);
        }
    }
    t.elapsed = began.elapsed();
    t
}

fn mib(bytes: usize) -> String {
    format!("{:.2} MiB", bytes as f64 / (1 << 20) as f64)
}

#[test]
fn every_decoder_survives_a_million_mutated_inputs() {
    let target: u64 = env_or("FUZZ_INPUTS", 1_000_000);
    let threads: usize = env_or("FUZZ_THREADS", 2);
    let began = Instant::now();
    // Two threads take the decoders in turn (the slowest first).
    let order = [
        Kind::Checkpoint,
        Kind::Hearing,
        Kind::Telemetry,
        Kind::Denials,
        Kind::Ready,
        Kind::Ack,
        Kind::Estimate,
        Kind::Start,
        Kind::TimeReply,
    ];
    assert_eq!(order.len(), KINDS.len());
    let next = std::sync::atomic::AtomicUsize::new(0);
    let results = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..threads.max(1) {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(&kind) = order.get(i) else { break };
                let t = fuzz(kind, target);
                eprintln!(
                    "{:<10} {:<32} {:>9} inputs ({} seeds, {} decode): {:>7} decoded, {:>7} refused, {} panics; \
                     largest allocation {} bytes (a {}-byte input; {:.0}% of its bound), peak {} bytes (a {}-byte \
                     input), largest allocation / length {:.1} (inputs of 64 bytes or more); {:.1} s",
                    kind.name(),
                    kind.decoder(),
                    t.inputs,
                    t.seeds,
                    t.seeds_decoded,
                    t.decoded,
                    t.refused,
                    t.panicked,
                    t.largest.0,
                    t.largest.1,
                    100.0 * t.bound_use,
                    t.peak.0,
                    t.peak.1,
                    t.ratio,
                    t.elapsed.as_secs_f64()
                );
                results.lock().unwrap().push((kind, t));
            });
        }
    });
    let results = results.into_inner().unwrap();
    let mut wrong = Vec::new();
    for (kind, t) in &results {
        let name = kind.name();
        if t.panicked > 0 {
            wrong.push(format!("{name}: {} inputs panicked, e.g. {:?}", t.panicked, t.panics));
        }
        if !t.over_bound.is_empty() {
            wrong.push(format!("{name}: allocations over 32 x length + 2 MiB: {:?}", t.over_bound));
        }
        if t.seeds_decoded != t.seeds {
            wrong.push(format!(
                "{name}: only {} of its {} captured messages decode (the format changed? capture the corpus \
                 again: cargo test --test it fuzz_decoders::capture_corpus -- --ignored)",
                t.seeds_decoded, t.seeds
            ));
        }
    }
    let largest = results.iter().map(|(_, t)| t.largest.0).max().unwrap_or(0);
    let ratio = results.iter().map(|(_, t)| t.ratio).fold(0.0, f64::max);
    let bound_use = results.iter().map(|(_, t)| t.bound_use).fold(0.0, f64::max);
    eprintln!(
        "all decoders: {} inputs, {} panics, largest single allocation {} ({largest} bytes: serde's first \
         allocation for a declared sequence), at most {:.0}% of an input's bound (32 x length + 2 MiB), largest \
         allocation / length {ratio:.1} (inputs of 64 bytes or more), in {:.1} s",
        results.iter().map(|(_, t)| t.inputs).sum::<u64>(),
        results.iter().map(|(_, t)| t.panicked).sum::<u64>(),
        mib(largest),
        100.0 * bound_use,
        began.elapsed().as_secs_f64()
    );
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

// ---------------------------------------------------------------------------
// The attacks named in the issue, exactly.

/// Decodes `bytes` with `kind`'s decoder under the counting allocator:
/// whether it decoded, and what it allocated.
fn attack(kind: Kind, bytes: &[u8]) -> (bool, Allocated) {
    let cx = Context::plain();
    let mut ok = false;
    let a = measure(|| ok = decode(kind, bytes, &cx, 0));
    (ok, a)
}

/// bincode's varint of a u64 (standard configuration).
fn varint(v: u64) -> Vec<u8> {
    match v {
        0..=250 => vec![v as u8],
        251..=0xFFFF => [vec![251], (v as u16).to_le_bytes().to_vec()].concat(),
        0x1_0000..=0xFFFF_FFFF => [vec![252], (v as u32).to_le_bytes().to_vec()].concat(),
        _ => [vec![253], v.to_le_bytes().to_vec()].concat(),
    }
}

#[test]
fn the_issues_attack_inputs_are_refused() {
    let huge = varint(1 << 62);
    // Telemetry: follower 1's batch with no samples whose `diverged` string
    // declares 2^62 bytes (the issue's was 46 bytes; the encoding of
    // `Counters` has grown since).
    let mut t = common::empty_follower_batch(1);
    if let Telemetry::Follower { diverged, .. } = &mut t {
        *diverged = Some(String::new());
    }
    let mut bytes = formation_protocol::codec::encode(&t);
    // `diverged` = Some(""), then `left` = None, end the encoding.
    assert_eq!(bytes[bytes.len() - 3..], [1, 0, 0], "Some(\"\"), None end the encoding");
    bytes.truncate(bytes.len() - 2);
    bytes.extend_from_slice(&huge);
    assert!(bytes.len() <= 64, "a telemetry batch of {} bytes: {}", bytes.len(), hex(&bytes));
    let (ok, a) = attack(Kind::Telemetry, &bytes);
    assert!(!ok, "telemetry declaring a 2^62-byte string decoded");
    assert!(a.largest <= bound(bytes.len()), "telemetry: {} bytes allocated", a.largest);
    eprintln!("{}-byte telemetry (diverged: 2^62 bytes) refused; {} bytes allocated at most", bytes.len(), a.largest);

    // Ready: 13 bytes, fingerprint 0 and one scenario key whose name declares
    // 2^62 bytes (the issue's); and the key list itself declaring 2^62 entries.
    let one_key = [vec![0, 1], huge.clone(), vec![0, 0]].concat();
    let many_keys = [vec![0], huge.clone(), vec![0, 0, 0]].concat();
    for (what, bytes) in [("a key of 2^62 bytes", one_key), ("2^62 keys", many_keys)] {
        assert_eq!(bytes.len(), 13, "{what}: {}", hex(&bytes));
        let (ok, a) = attack(Kind::Ready, &bytes);
        assert!(!ok, "Ready with {what} decoded");
        assert!(a.largest <= bound(bytes.len()), "Ready with {what}: {} bytes allocated", a.largest);
        eprintln!("13-byte Ready ({what}) refused; {} bytes allocated at most", a.largest);
    }

    // hearing.bin whose first length field (the scenario's label) is 2^62,
    // with and without a matching checksum.
    for crc_ok in [false, true] {
        let mut bytes =
            [varint(u64::from(formation_record::hearing::HEARING_FORMAT)), huge.clone(), vec![0; 8]].concat();
        let crc = if crc_ok { crc32(&bytes) } else { 0 };
        bytes.extend_from_slice(&crc.to_le_bytes());
        let mut r = None;
        let a = measure(|| r = Some(HearingRecord::decode(&bytes, "hearing.bin").map(|_| ())));
        assert!(matches!(r, Some(Err(HearingError::Malformed(_)))), "hearing.bin, label of 2^62 bytes: {r:?}");
        assert!(a.largest <= bound(bytes.len()), "hearing.bin: {} bytes allocated", a.largest);
        eprintln!(
            "{}-byte hearing.bin (first length 2^62, checksum {}) refused; {} bytes allocated at most",
            bytes.len(),
            if crc_ok { "matching" } else { "wrong" },
            a.largest
        );
    }
}

// ---------------------------------------------------------------------------
// Length fields at their extremes in large inputs: sequences of empty
// elements. bincode claims a read element's encoded primitives against its
// limit (8 bytes for an empty string's or list's length), not its size in
// memory (24 bytes for a `String` or `Vec`), and a `Vec` read by serde
// doubles its capacity as it grows (the old block is live while it moves):
// one byte of input can cost 2 × 24 = 48 bytes in one allocation and 72
// bytes at the peak. What those inputs allocate is measured here.

/// The worst shapes, with as many elements as make the vector's last growth
/// the longest (serde's first allocation of 1 MiB, doubled, plus one).
fn empties(kind: &str, n: usize) -> Vec<u8> {
    use formation_protocol::codec::encode;
    use formation_record::hearing::{Density, HeardRuns, ScenarioSource, HEARING_FORMAT};
    let follower = |slots: usize| {
        let mut t = common::empty_follower_batch(1);
        if let Telemetry::Follower { heard, .. } = &mut t {
            *heard = HeardRuns { steps: 0, slots: vec![vec![]; slots] };
        }
        t
    };
    match kind {
        "telemetry" => encode(&follower(n)),
        "ready" => encode(&Ready { fingerprint: 1, keys: vec![(String::new(), 0); n] }),
        "ack" => encode(&Ack { fingerprint: 1, next_k: vec![(0, 0); n] }),
        "hearing" => HearingRecord {
            format: HEARING_FORMAT,
            scenario: ScenarioSource { label: String::new(), text: String::new(), overrides: vec![String::new(); n] },
            fingerprint: 1,
            density: Density { every: 1, csv: false, mcap: false },
            leader: vec![],
            followers: vec![],
            rescued: vec![],
        }
        .encode(),
        _ => unreachable!(),
    }
}

#[test]
fn large_inputs_of_empty_elements() {
    let mut worst: f64 = 0.0;
    for (name, kind, element) in [
        ("telemetry", Kind::Telemetry, 24),
        ("ready", Kind::Ready, 32),
        ("ack", Kind::Ack, 16),
        ("hearing", Kind::Hearing, 24),
    ] {
        let first = (1 << 20) / element;
        for doublings in [4, 5] {
            let n = (first << doublings) + 1;
            let bytes = empties(name, n);
            let (ok, a) = attack(kind, &bytes);
            assert!(ok, "{name}: {n} empty elements do not decode");
            let ratio = a.largest as f64 / bytes.len() as f64;
            worst = worst.max(ratio);
            eprintln!(
                "{name:<9} {n:>8} empty elements, {:>8} bytes: largest allocation {} ({ratio:.1} x length, bound \
                 32 x length + 2 MiB = {}), peak {} ({:.1} x length)",
                bytes.len(),
                mib(a.largest),
                mib(bound(bytes.len())),
                mib(a.peak),
                a.peak as f64 / bytes.len() as f64
            );
            // What holds: 48 x length in one allocation, 72 x at the peak.
            assert!(a.largest <= 48 * bytes.len() + (2 << 20), "{name}: {} bytes in one allocation", a.largest);
            assert!(a.peak <= 72 * bytes.len() + (3 << 20), "{name}: a peak of {} bytes", a.peak);
        }
    }
    eprintln!("largest allocation of a large input: {worst:.1} x its length");
}

// ---------------------------------------------------------------------------
// The corpus: captured from real runs.

/// The capture's runs: name and duration (s); each run's router is on a
/// free loopback port (`common::Ports`). Three durations give three hearing
/// records of different lengths.
const CAPTURE_RUNS: [(&str, &str); 3] = [("fuzzcap", "1"), ("fuzzcap2", "0.2"), ("fuzzcap3", "0.05")];
/// Files kept per decoder.
const KEEP: usize = 20;

/// What one capture run gave: the messages heard (key, payload), the
/// leader's clock replies, hearing.bin and the agents' checkpoints.
struct Captured {
    heard: Vec<(String, Vec<u8>)>,
    replies: Vec<Vec<u8>>,
    hearing: Vec<u8>,
    checkpoints: Vec<(String, Vec<u8>)>,
}

/// One capture run (see [`capture_corpus`]).
fn capture_run(tmp: &Path, certs: &Path, run: &str, duration: &str) -> Captured {
    use formation_net::session::{self, ZenohArgs, ZenohMode};
    use std::os::unix::process::CommandExt;
    use std::sync::{Arc, Mutex};

    let out = tmp.join(run);
    // The agents write their checkpoints in $TMPDIR/formation-checkpoints.
    let tmpdir = tmp.join(format!("{run}-tmp"));
    std::fs::create_dir_all(&tmpdir).expect("tmp");
    let port = common::Ports::free(1).release();
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_formation"));
    cmd.args(["launch", common::SCENARIO, "-q", "--out"])
        .arg(&out)
        .args(["--set", &format!("duration={duration}"), "--set", "timing=lockstep"])
        .args(["--set", "network.telemetry_batch=10"])
        .args(["--mode", "client", "--base-port", &port.to_string(), "--run", run, "--tls"])
        .arg(certs)
        .env("TMPDIR", &tmpdir)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .process_group(0);
    let mut g = common::Group(cmd.spawn().expect("spawn formation launch"));
    // The newest checkpoint of each follower, read while the run lasts (an
    // agent removes its own when the run is complete).
    let mut checkpoints: std::collections::BTreeMap<String, Vec<u8>> = Default::default();
    let read_checkpoints = |into: &mut std::collections::BTreeMap<String, Vec<u8>>| {
        for e in std::fs::read_dir(tmpdir.join("formation-checkpoints")).into_iter().flatten().flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            if let (Some(stem), Ok(bytes)) = (name.strip_suffix(".json"), std::fs::read(e.path())) {
                into.insert(stem.to_string(), bytes);
            }
        }
    };

    /// Every (key, payload) heard, in order.
    type Heard = Arc<Mutex<Vec<(String, Vec<u8>)>>>;
    let heard: Heard = Arc::default();
    let mut replies: Vec<Vec<u8>> = Vec::new();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().expect("rt");
    let status = rt.block_on(async {
        let open_as = |name: &'static str| {
            let args = ZenohArgs {
                mode: Some(ZenohMode::Client),
                connect: vec![format!("tcp/127.0.0.1:{port}")],
                tls: Some(certs.to_path_buf()),
                identity: Some(name.into()),
                ..Default::default()
            };
            async move {
                tokio::time::timeout(Duration::from_secs(20), session::open(&args))
                    .await
                    .unwrap_or_else(|_| panic!("{name}: no session within 20 s"))
                    .unwrap_or_else(|e| panic!("{name}: {e}"))
            }
        };
        let listener = open_as("leader").await;
        // One subscriber per key pattern the leader's role may hear (the
        // access control refuses `formation/<run>/**`).
        let mut subs = Vec::new();
        for pattern in ["estimate/*", "telemetry/*", "control/**"] {
            let h = heard.clone();
            let sub = listener
                .declare_subscriber(format!("formation/{run}/{pattern}"))
                .callback(move |s| {
                    h.lock().unwrap().push((s.key_expr().as_str().to_string(), s.payload().to_bytes().into_owned()))
                })
                .await
                .expect("subscriber");
            subs.push(sub);
        }
        let asker = open_as("agent-1").await;
        let forger = open_as("agent-2").await;
        let began = Instant::now();
        loop {
            if let Some(status) = g.0.try_wait().expect("try_wait") {
                return status;
            }
            read_checkpoints(&mut checkpoints);
            assert!(began.elapsed() < Duration::from_secs(90), "the capture run did not end within 90 s");
            if let Ok(rx) = asker.get(format!("formation/{run}/control/time")).timeout(Duration::from_millis(500)).await
            {
                while let Ok(r) = rx.recv_async().await {
                    if let Ok(s) = r.result() {
                        replies.push(s.payload().to_bytes().into_owned());
                    }
                }
            }
            let forged = heard.lock().unwrap().iter().rev().find(|(k, _)| k.ends_with("/estimate/3")).cloned();
            if let Some((_, bytes)) = forged {
                let _ = forger.put(format!("formation/{run}/estimate/3"), bytes).await;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    });
    assert!(status.success(), "the capture run {run} failed: {status}");
    let heard = heard.lock().unwrap().clone();
    eprintln!("{run}: heard {} messages, {} clock replies", heard.len(), replies.len());
    let checkpoints: Vec<(String, Vec<u8>)> = checkpoints.into_iter().collect();
    // A short lock-step run may end before the 50 ms polls read one: the
    // capture as a whole needs some (asserted by capture_corpus).
    let left = std::fs::read_dir(tmpdir.join("formation-checkpoints")).map_or(0, |d| d.count());
    assert_eq!(left, 0, "a complete run left {left} checkpoints behind");
    let hearing = std::fs::read(out.join("hearing.bin")).expect("the run's hearing.bin");
    Captured { heard, replies, hearing, checkpoints }
}

/// Captures `tests/fuzz_corpus/` from real runs: `formation launch` of the
/// paper scenario (1 s, 0.2 s and 0.05 s, lock-step, telemetry batches of
/// 10 steps) over TLS in client mode on free loopback ports, while
/// sessions of this test, with the run's certificates, hear every key of
/// the run (as the leader, whose role hears them all), ask the leader's
/// clock (as agent 1, like a follower) and put agent 3's estimates on its
/// key as agent 2 (refused by the router's access control, which then
/// publishes its denial reports). The runs' hearing.bin and their agents'
/// checkpoints are copied too. Then per decoder at most [`KEEP`] distinct
/// payloads, spread over keys and over each run. Run by hand:
/// `cargo test --test it fuzz_decoders::capture_corpus -- --ignored`.
#[test]
#[ignore = "rewrites tests/fuzz_corpus from real runs"]
fn capture_corpus() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let certs = tmp.path().join("certs");
    common::certs(&certs);
    // Per decoder, the samples by key (in the order heard).
    let mut by: std::collections::BTreeMap<&str, std::collections::BTreeMap<String, Vec<Vec<u8>>>> = Default::default();
    for (run, duration) in CAPTURE_RUNS {
        let c = capture_run(tmp.path(), &certs, run, duration);
        let prefix = format!("formation/{run}/");
        for (key, bytes) in c.heard {
            let rest = key.strip_prefix(&prefix).unwrap_or(&key).to_string();
            let kind = match rest.as_str() {
                r if r.starts_with("estimate/") => "estimate",
                r if r.starts_with("telemetry/") => "telemetry",
                r if r.starts_with("control/ready/") => "ready",
                "control/start" => "start",
                "control/ack" => "ack",
                r if r.starts_with("control/denied/") => "denials",
                _ => continue,
            };
            by.entry(kind).or_default().entry(format!("{run}-{}", rest.replace('/', "-"))).or_default().push(bytes);
        }
        by.entry("timereply").or_default().insert(format!("{run}-control-time"), c.replies);
        for (name, bytes) in c.checkpoints {
            by.entry("checkpoint").or_default().insert(name, vec![bytes]);
        }
        by.entry("hearing").or_default().insert(format!("{run}-hearing"), vec![c.hearing]);
    }
    assert!(by.get("checkpoint").is_some_and(|c| !c.is_empty()), "no checkpoint read during any capture run");

    for kind in KINDS {
        let dir = corpus_dir().join(kind.name());
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("corpus folder");
        let keys = by.remove(kind.name()).unwrap_or_default();
        // Distinct payloads, spread over the run: round robin over the keys,
        // each key's samples taken evenly from first to last.
        let lists: Vec<(String, Vec<Vec<u8>>)> = keys
            .into_iter()
            .map(|(k, mut v)| {
                let mut seen = std::collections::HashSet::new();
                v.retain(|b| seen.insert(b.clone()));
                (k, v)
            })
            .filter(|(_, v)| !v.is_empty())
            .collect();
        let total: usize = lists.iter().map(|(_, v)| v.len()).sum();
        assert!(total > 0, "nothing captured for {}", kind.name());
        let per_key = KEEP.div_ceil(lists.len()).max(1);
        let mut kept = 0;
        for (key, list) in &lists {
            let n = per_key.min(list.len()).min(KEEP - kept);
            for j in 0..n {
                let at = if n == 1 { list.len() - 1 } else { j * (list.len() - 1) / (n - 1) };
                let ext = if kind.json() { "json" } else { "bin" };
                std::fs::write(dir.join(format!("{key}-{at:04}.{ext}")), &list[at]).expect("corpus file");
                kept += 1;
            }
        }
        eprintln!("{}: kept {kept} of {total} distinct messages", kind.name());
    }
}

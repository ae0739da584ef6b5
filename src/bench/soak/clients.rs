//! The soak's own clients: fast, stalled, slow, cancelling and uploading, and the newcomer
//! timed at every reading (what every client shares is `bench::clients`).

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::time::timeout_at;

use crate::bench::clients::{all_fields, Shared};
use crate::service::client::{connect, Client};
use crate::service::pb;

/// A fast client: rank `rank` of `world`, read as fast as it comes until `until`; checks that
/// every index is the next of its rank, resumes an interrupted stream from its cursor.
pub(super) async fn fast_client(
    addr: String,
    seed: u64,
    rank: u32,
    world: u32,
    until: tokio::time::Instant,
    sh: Arc<Shared>,
) {
    let mut client = match timeout_at(until, connect(&addr)).await {
        Ok(Ok(c)) => c,
        Ok(Err(e)) => return sh.error("fast", "connect", &e.to_string(), false),
        Err(_) => return,
    };
    let step = u64::from(world);
    let mut expected = u64::from(rank);
    let mut start = 0u64;
    while tokio::time::Instant::now() < until {
        let req = pb::StreamRequest {
            rank,
            world_size: world,
            start_index: start,
            ..pb::SampleSpec { seed, ..Default::default() }.stream()
        };
        let mut stream = match timeout_at(until, client.stream_samples(req)).await {
            Ok(Ok(s)) => s.into_inner(),
            Ok(Err(s)) => {
                sh.status("fast", &s, true);
                continue;
            }
            Err(_) => return,
        };
        // a timeout polls its future first: a stream that is always ready never times out
        let mut last = tokio::time::Instant::now();
        while tokio::time::Instant::now() < until {
            match timeout_at(until, stream.message()).await {
                Err(_) => return,
                Ok(Ok(Some(batch))) => {
                    let now = tokio::time::Instant::now();
                    sh.fast_max_gap_us.fetch_max((now - last).as_micros() as u64, Ordering::Relaxed);
                    last = now;
                    for s in &batch.samples {
                        if s.index == expected {
                            expected += step;
                        } else if s.index < expected {
                            sh.repeated.fetch_add(1, Ordering::Relaxed);
                        } else {
                            let gap = (s.index - expected) / step;
                            sh.lost.fetch_add(gap.max(1), Ordering::Relaxed);
                            expected = s.index + step;
                        }
                        sh.fast_samples.fetch_add(1, Ordering::Relaxed);
                    }
                    start = batch.resume_start_index;
                }
                Ok(Ok(None)) => {
                    sh.error("fast", "stream ended", "an endless stream ended", false);
                    break;
                }
                Ok(Err(s)) => {
                    sh.status("fast", &s, true);
                    if let Some((_, resume)) = crate::service::error::cursor_of(&s) {
                        start = resume;
                    }
                    break;
                }
            }
        }
    }
}

async fn connected(kind: &str, addr: &str, until: tokio::time::Instant, sh: &Shared) -> Option<Client> {
    match timeout_at(until, connect(addr)).await {
        Ok(Ok(c)) => Some(c),
        Ok(Err(e)) => {
            sh.error(kind, "connect", &e.to_string(), false);
            None
        }
        Err(_) => None,
    }
}

/// Opens a stream with prefetch 64, every field and `batch` samples per message, reads one
/// batch, stops reading for `hold`.
#[allow(clippy::too_many_arguments)] // the client's shape: its stream, its pause, its address
pub(super) async fn stalled_client(
    addr: String,
    seed: u64,
    batch: u32,
    frames: u32,
    hold: Duration,
    from: Option<std::net::IpAddr>,
    until: tokio::time::Instant,
    sh: Arc<Shared>,
) {
    let Some(mut client) = sh.connect("stalled", &addr, from, until).await else { return };
    let mut round = 0u64;
    while tokio::time::Instant::now() < until {
        let req = pb::StreamRequest {
            prefetch: 64,
            batch_size: batch,
            ..pb::SampleSpec { seed: seed + round, fields: all_fields(), frames, ..Default::default() }.stream()
        };
        round += 1;
        match timeout_at(until, client.stream_samples(req)).await {
            Ok(Ok(s)) => {
                let mut s = s.into_inner();
                sh.stalled_streams.fetch_add(1, Ordering::Relaxed);
                match timeout_at(until, s.message()).await {
                    Ok(Err(status)) => sh.status("stalled", &status, false),
                    Ok(Ok(_)) => {
                        // stop reading: the server holds what it made for this stream
                        let wake = (tokio::time::Instant::now() + hold).min(until);
                        tokio::time::sleep_until(wake).await;
                    }
                    Err(_) => return,
                }
            }
            Ok(Err(status)) => {
                sh.status("stalled", &status, false);
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(_) => return,
        }
    }
}

/// A newcomer: a new connection and a GetInfo call; its wait in ms, or None when turned away.
pub(super) async fn newcomer(addr: &str) -> Option<f64> {
    let t = Instant::now();
    let mut c = tokio::time::timeout(Duration::from_secs(60), connect(addr)).await.ok()?.ok()?;
    tokio::time::timeout(Duration::from_secs(60), c.get_info(pb::InfoRequest {})).await.ok()?.ok()?;
    Some(t.elapsed().as_secs_f64() * 1e3)
}

/// Reads one batch every 250 ms.
pub(super) async fn slow_client(addr: String, seed: u64, until: tokio::time::Instant, sh: Arc<Shared>) {
    let Some(mut client) = connected("slow", &addr, until, &sh).await else { return };
    while tokio::time::Instant::now() < until {
        let req = pb::SampleSpec { seed, ..Default::default() }.stream();
        let mut s = match timeout_at(until, client.stream_samples(req)).await {
            Ok(Ok(s)) => s.into_inner(),
            Ok(Err(status)) => {
                sh.status("slow", &status, false);
                tokio::time::sleep(Duration::from_millis(200)).await;
                continue;
            }
            Err(_) => return,
        };
        while tokio::time::Instant::now() < until {
            match timeout_at(until, s.message()).await {
                Ok(Ok(Some(b))) => {
                    sh.slow_samples.fetch_add(b.samples.len() as u64, Ordering::Relaxed);
                }
                Ok(Ok(None)) => break,
                Ok(Err(status)) => {
                    sh.status("slow", &status, false);
                    break;
                }
                Err(_) => return,
            }
            // the client's pace, not a wait for the server
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }
}

/// Opens streams and drops them after 0 to 3 batches; every other time a GetSamples read once.
pub(super) async fn cancelling_client(addr: String, seed: u64, until: tokio::time::Instant, sh: Arc<Shared>) {
    let Some(mut client) = connected("cancelling", &addr, until, &sh).await else { return };
    let mut round = 0u64;
    while tokio::time::Instant::now() < until {
        round += 1;
        let reads = round % 4;
        let opened = if round.is_multiple_of(2) {
            let req = pb::SampleSpec { seed, ..Default::default() }.samples(vec![round, round + 7, round * 3]);
            match timeout_at(until, client.get_samples(req)).await {
                Ok(Ok(s)) => {
                    let mut s = s.into_inner();
                    if let Ok(Err(status)) = timeout_at(until, s.message()).await {
                        sh.status("cancelling", &status, false);
                    }
                    Ok(())
                }
                Ok(Err(status)) => Err(status),
                Err(_) => return,
            }
        } else {
            let req = pb::StreamRequest {
                start_index: round * 100,
                ..pb::SampleSpec { seed, ..Default::default() }.stream()
            };
            match timeout_at(until, client.stream_samples(req)).await {
                Ok(Ok(s)) => {
                    let mut s = s.into_inner();
                    for _ in 0..reads {
                        match timeout_at(until, s.message()).await {
                            Ok(Ok(Some(_))) => {}
                            Ok(Ok(None)) => break,
                            Ok(Err(status)) => {
                                sh.status("cancelling", &status, false);
                                break;
                            }
                            Err(_) => return,
                        }
                    }
                    Ok(())
                }
                Ok(Err(status)) => Err(status),
                Err(_) => return,
            }
        };
        match opened {
            Ok(()) => {
                sh.cancelled_streams.fetch_add(1, Ordering::Relaxed);
            }
            Err(status) => {
                sh.status("cancelling", &status, false);
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    }
}

/// The chunks of an upload of two small photos with depth (`.npy`) to `dataset`.
fn upload_chunks(dataset: &str, round: u64) -> Vec<pb::SourceChunk> {
    let (w, h) = (80u32, 60u32);
    let mut chunks = Vec::new();
    for k in 0..2u32 {
        let r = (round % 200) as u32;
        let img = ::image::RgbImage::from_fn(w, h, |x, y| {
            ::image::Rgb([(x * 3 + r) as u8, (y * 4 + k * 60) as u8, ((x ^ y) + r) as u8])
        });
        let mut png = std::io::Cursor::new(Vec::new());
        if img.write_to(&mut png, ::image::ImageFormat::Png).is_err() {
            continue;
        }
        let depth: Vec<f32> = (0..w * h).map(|i| 2.0 + (i % w) as f32 / w as f32).collect();
        let mut npy = Vec::new();
        if crate::io::npy::write_f32_to(&mut npy, &[u64::from(h), u64::from(w)], &depth).is_err() {
            continue;
        }
        let name = format!("photo{k}");
        let png = png.into_inner();
        // the image in two chunks, as a client streaming a file does
        let half = png.len() / 2;
        chunks.push(pb::SourceChunk {
            dataset: dataset.into(),
            name: name.clone(),
            kind: "image".into(),
            data: png[..half].to_vec(),
        });
        chunks.push(pb::SourceChunk { data: png[half..].to_vec(), ..Default::default() });
        chunks.push(pb::SourceChunk { name, kind: "depth".into(), data: npy, ..Default::default() });
    }
    chunks
}

/// Uploads two photos with depth to its dataset once a second, checks both are accepted, pulls
/// two samples of it.
pub(super) async fn uploading_client(addr: String, k: usize, until: tokio::time::Instant, sh: Arc<Shared>) {
    let Some(mut client) = connected("uploading", &addr, until, &sh).await else { return };
    let dataset = format!("soak-upload-{k}");
    let mut round = 0u64;
    while tokio::time::Instant::now() < until {
        round += 1;
        let chunks = upload_chunks(&dataset, round);
        match timeout_at(until, client.upload_sources(tokio_stream::iter(chunks))).await {
            Ok(Ok(r)) => {
                let sum = r.into_inner();
                if sum.accepted != 4 || !sum.rejected.is_empty() {
                    let m = format!("accepted {} of 4, rejected {:?}", sum.accepted, sum.rejected);
                    sh.error("uploading", "not accepted", &m, false);
                } else {
                    sh.uploads.fetch_add(1, Ordering::Relaxed);
                    let req = pb::StreamRequest {
                        count: 2,
                        ..pb::SampleSpec { dataset: dataset.clone(), seed: round, ..Default::default() }.stream()
                    };
                    match timeout_at(until, crate::service::client::pull(&mut client, req, |_| {})).await {
                        Ok(Ok(p)) => {
                            if let Some(s) = p.error {
                                sh.status("uploading", &s, false);
                            } else if p.samples != 2 {
                                sh.error("uploading", "short pull", &format!("{} of 2 samples", p.samples), false);
                            }
                        }
                        Ok(Err(s)) => sh.status("uploading", &s, false),
                        Err(_) => return,
                    }
                }
            }
            Ok(Err(status)) => sh.status("uploading", &status, false),
            Err(_) => return,
        }
        // the client's pace: one upload a second
        tokio::time::sleep_until((tokio::time::Instant::now() + Duration::from_secs(1)).min(until)).await;
    }
}

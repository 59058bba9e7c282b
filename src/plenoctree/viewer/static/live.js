// A run folder (plenoctree view OUT, viewer/live.py): the server's live.json says where the run
// stands (stage, step, PSNR, ETA) and which tree is the newest; when a newer one lands the page
// reloads itself, keeping its camera across the reload (sessionStorage).

const LIVE_CAMERA = "plenoctree-live-camera";

// The corner line of a live.json status.
export function liveText(s) {
  const parts = [s.stage || "run"];
  if (s.step != null) parts.push(`step ${s.step}${s.steps ? ` of ${s.steps}` : ""}`);
  if (s.psnr != null && Number.isFinite(Number(s.psnr))) parts.push(`${Number(s.psnr).toFixed(2)} dB`);
  if (s.eta_s != null && s.eta_s > 0) {
    const m = Math.round(s.eta_s / 60);
    parts.push(m >= 1 ? `ETA ${m} min` : `ETA ${Math.round(s.eta_s)} s`);
  }
  parts.push(s.tree ? `showing ${decodeURIComponent(s.tree.split("/").pop())}` : "no tree yet");
  return parts.join(" \u00b7 ") + (s.error ? ` (newest tree unreadable: ${s.error})` : "");
}

// Poll live.json every 2 s into #live; reload when its version differs from the page's
// (config.version). cameraState(): the camera to keep (null before the tree is shown).
export function startLive(config, cameraState) {
  const el = document.getElementById("live");
  const poll = async () => {
    try {
      const r = await fetch("live.json", { cache: "no-store" });
      if (r.ok) {
        const s = await r.json();
        el.textContent = liveText(s);
        if (s.version && s.version !== (config.version || "")) {
          const cam = cameraState();
          if (cam) sessionStorage.setItem(LIVE_CAMERA, JSON.stringify(cam));
          location.reload();
          return;
        }
      }
    } catch (err) {
      el.textContent = "the viewer's server does not answer (did the view stop?)";
    }
    setTimeout(poll, 2000);
  };
  poll();
}

// After the first view is framed: the camera the page had before a live reload.
export function restoreLiveCamera(config, camera) {
  const saved = config.live && sessionStorage.getItem(LIVE_CAMERA);
  if (!saved) return;
  try { camera.setState(JSON.parse(saved)); } catch (err) { /* a stale entry: keep the view */ }
}

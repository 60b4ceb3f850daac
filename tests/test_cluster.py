"""Per-photo and per-tile work on a real Dask cluster (``LocalCluster``, 2 worker processes):
the same products as the local pool, a worker killed mid-run, and the refusals."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import rasterio
from test_sfm import _centre_errors, _truth

from geoortho.core.parallel import SCHEDULER_ENV, use_scheduler
from geoortho.errors import InputError

distributed = pytest.importorskip("distributed", reason="the dev set-up installs dask.distributed")


@pytest.fixture(scope="module")
def cluster():
    # Dask's nannies set OMP_NUM_THREADS=1 (and MKL, OpenBLAS) in *this* process's environment for
    # their workers: every process the test session starts later would inherit it, single-threaded
    saved = dict(os.environ)
    try:
        with distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
        ) as c:
            yield c
    finally:
        os.environ.clear()
        os.environ.update(saved)


@pytest.fixture(scope="module")
def local_gcp_find(small_survey, tmp_path_factory):
    """gcp-find on the small survey with the local pool: what every cluster run must give."""
    from geoortho.gcp.find import gcp_find

    d = tmp_path_factory.mktemp("local_gcp")
    return gcp_find(small_survey.images, small_survey.gcp_file, d / "local.txt", detections=d / "l.csv"), d


def _geoortho(*args: str, **run: object) -> subprocess.CompletedProcess[str]:
    """``python -m geoortho ARGS`` in a child, its output captured."""
    return subprocess.run([sys.executable, "-m", "geoortho", *args], capture_output=True, text=True, **run)


def test_gcp_find_on_the_cluster_is_the_local_run(cluster, small_survey, local_gcp_find, tmp_path):
    from geoortho.gcp.find import gcp_find

    local, d = local_gcp_find
    with use_scheduler(cluster.scheduler_address, must_see=[small_survey.images]) as client:
        with distributed.get_task_stream(client) as ts:
            on = gcp_find(
                small_survey.images, small_survey.gcp_file, tmp_path / "dask.txt", detections=tmp_path / "d.csv"
            )
        n_tasks = len(ts.data)
    assert n_tasks >= len(list(small_survey.images.glob("*.JPG")))  # every photo's detection ran there
    assert local.n_observations == on.n_observations > 50
    assert (d / "local.txt").read_bytes() == (tmp_path / "dask.txt").read_bytes()
    assert (d / "l.csv").read_bytes() == (tmp_path / "d.csv").read_bytes()


def test_synth_rendering_on_the_cluster_is_the_local_run(cluster, tiny_survey, tmp_path):
    from geoortho.synthetic.survey import synth

    with use_scheduler(cluster.scheduler_address, must_see=[tmp_path]) as client:
        with distributed.get_task_stream(client) as ts:
            r = synth(tmp_path / "tiny", preset="tiny", seed=3)
        n_tasks = len(ts.data)
    assert n_tasks >= r.n_photos
    for mine in sorted(r.images.glob("*.JPG")):
        assert mine.read_bytes() == (tiny_survey.images / mine.name).read_bytes(), mine.name


def test_ortho_tiles_on_the_cluster_are_the_local_run(cluster, tiny_survey, tmp_path):
    import json

    from geoortho.orthophoto.mosaic import ortho

    home = json.loads((tiny_survey.truth / "survey.json").read_text())["home"]
    args = dict(dsm=tiny_survey.dsm, takeoff_elevation_m=home["ground_z"], tile_px=256)
    ortho(tiny_survey.images, tmp_path / "local.tif", workers=2, **args)
    with use_scheduler(cluster.scheduler_address, must_see=[tiny_survey.images, tmp_path]) as client:
        with distributed.get_task_stream(client) as ts:
            ortho(tiny_survey.images, tmp_path / "dask.tif", **args)
        n_tasks = len(ts.data)
    assert n_tasks >= 4
    with rasterio.open(tmp_path / "local.tif") as a, rasterio.open(tmp_path / "dask.tif") as b:
        assert a.profile == b.profile
        assert np.array_equal(a.read(), b.read())


def test_photo_metadata_and_footprints_on_the_cluster_are_the_local_run(cluster, small_survey, tmp_path, monkeypatch):
    import geopandas as gpd

    import geoortho.photos.metadata as photos
    from geoortho.photos.footprint import footprints

    monkeypatch.setattr(photos, "PHOTOS_PER_CHUNK", 8)  # 5 chunks: past the 4 from which a pool is used
    footprints(small_survey.images, tmp_path / "local.gpkg", dsm=small_survey.dsm)
    with use_scheduler(cluster.scheduler_address, must_see=[small_survey.images, tmp_path]) as client:
        with distributed.get_task_stream(client) as ts:
            footprints(small_survey.images, tmp_path / "dask.gpkg", dsm=small_survey.dsm)
        n_tasks = len(ts.data)
    assert n_tasks >= 5
    a, b = gpd.read_file(tmp_path / "local.gpkg"), gpd.read_file(tmp_path / "dask.gpkg")
    assert len(a) == len(list(small_survey.images.glob("*.JPG")))
    assert a.equals(b)


def test_dense_depth_maps_on_the_cluster_are_the_local_run(cluster, sfm_with_gcps, small_survey, tmp_path):
    import laspy

    from geoortho.reconstruction.dense import dense

    r_sfm, _ = sfm_with_gcps
    args = dict(max_image_size=320)  # the depth maps' size: the product, not the survey, is compared
    local = dense(r_sfm.output, small_survey.images, tmp_path / "local.laz", workers=2, **args)
    with use_scheduler(cluster.scheduler_address, must_see=[small_survey.images, r_sfm.output, tmp_path]) as client:
        with distributed.get_task_stream(client) as ts:
            on = dense(r_sfm.output, small_survey.images, tmp_path / "dask.laz", **args)
        n_tasks = len(ts.data)
    # a depth map a registered photo (the SfM may leave one of the 35 out; its own test counts them)
    assert n_tasks >= on.n_photos == local.n_photos >= 0.9 * len(list(small_survey.images.glob("*.JPG")))
    assert local.n_points == on.n_points > 100_000
    a, b = laspy.read(tmp_path / "local.laz"), laspy.read(tmp_path / "dask.laz")
    for dim in ("X", "Y", "Z", "red", "green", "blue"):
        assert np.array_equal(a[dim], b[dim]), dim


_MMAPPED = """
def mmapped_mib(_=None):
    import ctypes, numpy as np
    class _Info(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in
                    "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]
    info = ctypes.CDLL(None).mallinfo2
    info.restype = _Info
    for _ in range(2):  # the second array comes after one was freed, as tile after tile
        before = info().hblkhd
        a = np.ones(1 << 20)  # 8 MiB, as a mosaic tile's planes
        held = (info().hblkhd - before) / 2**20  # MiB it took in mmapped blocks (zeroed, faulted anew)
        del a
    return held
"""


def test_cluster_workers_reuse_freed_arrays(cluster):
    """Dask's nanny fixes MALLOC_TRIM_THRESHOLD_ in its workers, which turns off glibc's dynamic mmap
    threshold: every array is a fresh mmap, zeroed and faulted in again (mosaic tiles 45 % slower
    than in a local pool). geoortho's tasks restore it in each worker: an 8 MiB array asked for
    after one was freed comes from the heap, as in a plain process."""
    from geoortho.core.parallel import map_ordered

    ns: dict = {}
    exec(_MMAPPED, ns)
    fixed = subprocess.run(
        [sys.executable, "-c", _MMAPPED + "print(mmapped_mib())"],
        capture_output=True,
        text=True,
        env=os.environ | {"MALLOC_TRIM_THRESHOLD_": "65536"},
        check=True,
    )
    assert float(fixed.stdout) >= 8  # the premise: fixed, the array is mmapped every time
    with use_scheduler(cluster.scheduler_address) as client:
        env = client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
        assert set(env.values()) == {"65536"}, env  # the nanny's setting, which the task undoes
        per_task = map_ordered(ns["mmapped_mib"], range(4), workers=2)
    assert max(per_task) == 0, per_task


def test_dem_tiles_on_the_cluster_are_the_local_run(cluster, small_survey, tmp_path, monkeypatch):
    import geoortho.elevation.tiles as demtiles
    from geoortho.elevation.gridding import dem

    monkeypatch.setattr(demtiles, "WHOLE_GRID_MAX_CELLS", 0)  # tiles (6 of them) on a small cloud
    monkeypatch.setattr(demtiles, "TILE_CELLS", 64)
    args = dict(dtm=tmp_path / "l_dtm.tif", classified=tmp_path / "l.laz")
    local = dem(small_survey.points, tmp_path / "l.tif", **args)
    with use_scheduler(cluster.scheduler_address, must_see=[small_survey.points, tmp_path]) as client:
        with distributed.get_task_stream(client) as ts:
            on = dem(small_survey.points, tmp_path / "d.tif", dtm=tmp_path / "d_dtm.tif", classified=tmp_path / "d.laz")
        n_tasks = len(ts.data)
    n_tiles = int(next(n for n in on.notes if "tiles" in n).split()[2])
    assert n_tasks >= n_tiles >= 4
    assert (local.n_points, local.n_ground) == (on.n_points, on.n_ground)
    for a, b in (("l.tif", "d.tif"), ("l_dtm.tif", "d_dtm.tif")):
        with rasterio.open(tmp_path / a) as x, rasterio.open(tmp_path / b) as y:
            assert np.array_equal(x.read(), y.read())
    import laspy

    assert np.array_equal(laspy.read(tmp_path / "l.laz").classification, laspy.read(tmp_path / "d.laz").classification)


def test_a_worker_killed_mid_run_does_not_change_the_result(cluster, small_survey, local_gcp_find, tmp_path):
    from geoortho.gcp.find import gcp_find

    _, d = local_gcp_find
    killed: list[int] = []
    with use_scheduler(cluster.scheduler_address) as client:
        pids = client.run(os.getpid)

        def kill_when_busy() -> None:
            # as soon as the scheduler has work on a worker, SIGKILL that worker's process
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not killed:
                busy = [w for w, tasks in client.processing().items() if tasks]
                if busy:
                    os.kill(pids[busy[0]], signal.SIGKILL)
                    killed.append(pids[busy[0]])
                time.sleep(0.05)

        killer = threading.Thread(target=kill_when_busy)
        killer.start()
        gcp_find(small_survey.images, small_survey.gcp_file, tmp_path / "dask.txt")
        killer.join()
        assert killed, "no worker was busy to kill"
        # the nanny started a new worker process in place of the killed one
        client.wait_for_workers(2, timeout=30)
        assert killed[0] not in client.run(os.getpid).values()
    assert (d / "local.txt").read_bytes() == (tmp_path / "dask.txt").read_bytes()


def test_a_scheduler_that_does_not_answer_is_one_line_exit_2_within_10_s(tmp_path):
    env = {**os.environ, SCHEDULER_ENV: "tcp://127.0.0.1:9"}  # the discard port: nobody listens
    t = time.monotonic()
    p = _geoortho("footprints", "--images", str(tmp_path), "--output", "f.gpkg", env=env, cwd=tmp_path)
    elapsed = time.monotonic() - t
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "tcp://127.0.0.1:9 does not answer" in lines[0], p.stderr
    assert elapsed < 10 + 5  # the connect timeout and a start-up


def test_workers_that_do_not_see_the_photos_are_refused(cluster, small_survey, tmp_path):
    """A worker in its own mount namespace, with an empty file system over the photos' folder."""
    if shutil.which("unshare") is None or os.geteuid() != 0:
        pytest.fail("this test needs util-linux unshare and root (the CI machine has both)")
    photos = tmp_path / "photos"
    shutil.copytree(small_survey.images, photos)
    scheduler = distributed.LocalCluster(n_workers=0, processes=True, dashboard_address=None, silence_logs=40)
    worker = subprocess.Popen(
        [
            "unshare",
            "--mount",
            "--propagation",
            "private",
            "sh",
            "-c",
            f'mount -t tmpfs none "{tmp_path}" && exec "{sys.executable}" -m distributed.cli.dask_worker '
            f"{scheduler.scheduler_address} --nworkers 1 --nthreads 1 --no-dashboard",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        with pytest.raises(InputError, match=r"does not see .*photos.*shared file system"):
            with use_scheduler(scheduler.scheduler_address, must_see=[photos], timeout_s=30):
                pass
        # the same check through the CLI: exit 2, one line
        p = _geoortho(
            "footprints", "--images", str(photos), "--output", str(tmp_path / "f.gpkg"),
            "--scheduler", scheduler.scheduler_address,
        )  # fmt: skip
        assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
        assert "does not see" in p.stderr
        assert not (tmp_path / "f.gpkg").exists()
    finally:
        worker.terminate()
        worker.wait(timeout=30)
        scheduler.close()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_scheduler_killed_mid_run_stops_the_run_with_one_line_and_no_product(small_survey, tmp_path):
    """A real ``dask scheduler`` and ``dask worker`` (processes of their own); the scheduler is
    SIGKILLed while its workers hold gcp-find's tasks: the run ends at once, exit 1, its last line
    says the scheduler was lost and what to do, Dask's reconnection tracebacks are not on stderr,
    and the output folder is as it was (no product, no temporary)."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = dict(stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    scheduler = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
         "--no-dashboard"], **quiet,
    )  # fmt: skip
    worker = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nworkers", "2", "--nthreads", "1",
         "--no-dashboard"], **quiet,
    )  # fmt: skip
    out = tmp_path / "out"
    out.mkdir()
    try:
        with distributed.Client(address, timeout=30, set_as_default=False) as watcher:
            watcher.wait_for_workers(2, timeout=60)
            run = subprocess.Popen(
                [sys.executable, "-m", "geoortho", "gcp-find", "--images", str(small_survey.images), "--gcp-file",
                 str(small_survey.gcp_file), "--output", str(out / "gcp_list.txt"), "--scheduler", address],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            )  # fmt: skip
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline and run.poll() is None:
                if any(watcher.processing().values()):
                    break
                time.sleep(0.02)
            assert run.poll() is None, "the run ended before any task was on a worker"
        scheduler.send_signal(signal.SIGKILL)
        killed_at = time.monotonic()
        _, err = run.communicate(timeout=120)
        took_s = time.monotonic() - killed_at
    finally:
        for p in (worker, scheduler):
            p.kill()
            p.wait(timeout=30)
    assert run.returncode == 1, err
    last = err.strip().splitlines()[-1]
    assert f"the Dask scheduler at {address} was lost mid-run" in last and "run again" in last, err
    assert "Traceback" not in err and "distributed.client" not in err, err
    assert took_s < 30, took_s  # Dask's reconnection gives up after the client's 10 s at most
    assert list(out.iterdir()) == []


@pytest.fixture(scope="module")
def split_on_cluster(cluster, sfm_with_gcps, small_survey, tmp_path_factory):
    """The small survey's SfM split in two submodels (each a task on the cluster), merged; and the
    number of tasks the cluster ran."""
    from geoortho.reconstruction.sparse import sfm

    whole, checkpoints = sfm_with_gcps
    gcp_list = whole.output.parent / "gcp_list.txt"
    d = tmp_path_factory.mktemp("split")
    kw = dict(gcp_list=gcp_list, checkpoints=",".join(checkpoints), split=20, max_image_size=1024, max_features=4096)
    with use_scheduler(cluster.scheduler_address, must_see=[small_survey.images, gcp_list, d]) as client:
        with distributed.get_task_stream(client) as ts:
            r = sfm(small_survey.images, d / "split", **kw)
        # this survey's photos are read here: the cluster's tasks are the submodels
        return r, len(ts.data)


def test_split_merge_submodels_on_the_cluster_make_one_model(split_on_cluster, sfm_with_gcps, small_survey):
    """Each submodel is a task on a worker; the merged model is one model, as accurate as the whole
    block's (the local split-merge runs the same submodels in this process: test_sfm's failed
    submodel runs it; COLMAP's threads do not repeat bit for bit)."""
    import json

    import geopandas as gpd
    import laspy

    whole, checkpoints = sfm_with_gcps
    r, n_tasks = split_on_cluster
    rep = json.loads(r.report.read_text())
    subs = rep["submodels"]
    assert len(subs) == 2 and n_tasks >= 2 and all(s["registered"] >= 20 for s in subs), n_tasks
    assert subs[1]["shared_photos"] >= 3 and subs[1]["shared_centre_rms_m"] < 0.05
    assert r.n_registered >= 0.95 * r.n_photos and rep["models"] == 2 and "split-merge" in rep["matching"]
    # one camera body, one camera: the submodels' calibrations of it are one after the merge
    assert len(rep["intrinsics"]) == 1, rep["intrinsics"]
    # its lens distortion decided as both submodels did, not tested again on the merged block; and
    # as the whole block decided (the synthetic lens has none: held at zero)
    folders = [r.report.parent / "submodels" / f"submodel_{s['submodel']:02d}" for s in subs]
    sub_held = {
        json.loads((f / "report.json").read_text())["intrinsics"][0]["distortion"]["held_at_zero"] for f in folders
    }
    whole_held = json.loads(whole.report.read_text())["intrinsics"][0]["distortion"]["held_at_zero"]
    assert sub_held == {whole_held} == {rep["intrinsics"][0]["distortion"]["held_at_zero"]}, (sub_held, whole_held)
    assert any("2 submodels each decided" in n for n in rep["notes"]), rep["notes"]
    # one model: every photo once, one georeference, GCP-controlled
    cams = gpd.read_file(r.cameras)
    assert cams.image.is_unique and len(cams) == r.n_photos
    # each registered photo says which submodel placed it; both submodels placed some
    reg = cams[cams.registered]
    assert set(reg.submodel) == {0, 1} and (cams[~cams.registered].submodel == -1).all()
    assert "GCP" in r.georeferenced_by
    poses = _truth(small_survey)[0]
    e_split = float(np.sqrt((_centre_errors(r, poses) ** 2).sum(axis=1).mean()))
    e_whole = float(np.sqrt((_centre_errors(whole, poses) ** 2).sum(axis=1).mean()))
    # the local split-merge of this survey: 0.013 m shared-centre RMS, checkpoints 0.0045 m (README).
    # With the lens distortion held at zero (the synthetic camera has none) the centres are 0.030 m
    # off (whole block: 0.023 m), all of it one vertical offset (+0.029 m, horizontal 2-3 mm): the
    # focal length came out 0.02-0.06 % long and the flying height follows it; the ground does not
    # (checkpoints 0.0023 m, whole block 0.0021 m)
    assert e_split <= max(2 * e_whole, 0.01) and e_split <= 0.035, (e_split, e_whole)
    assert r.checkpoint_rmse_m <= max(2 * whole.checkpoint_rmse_m, 0.01), r.checkpoint_rmse_m
    assert 0 < r.mean_reprojection_error_px < 1.0
    with laspy.open(r.points) as f:
        assert f.header.point_count > 1000
    # the same photos' cameras as the unsplit block's, within a GSD (issue 78)
    gsd = json.loads((small_survey.truth / "survey.json").read_text())["gsd_cm_at_home_height"] / 100
    a, b = gpd.read_file(r.cameras, layer="cameras"), gpd.read_file(whole.cameras, layer="cameras")
    both = a[a.registered].merge(b[b.registered], on="image", suffixes=("_split", "_whole"))
    dh = np.hypot(both.x_split - both.x_whole, both.y_split - both.y_whole)
    dz = (both.z_split - both.z_whole).abs()
    assert len(both) >= 0.9 * r.n_photos and dh.max() <= gsd and dz.max() <= gsd, (dh.max(), dz.max(), gsd)


def test_the_merged_products_show_no_step_along_the_submodel_border(split_on_cluster, small_survey, tmp_path):
    """Issue 78: the DSM and orthophoto made from the merged model, checked against the truth on
    both sides of where the two submodels meet. The border crosses a building and passes beside two
    GCPs (checked first: the survey is the case the issue names). Measured, from depth maps at 320
    px: open ground 0.13 GSD apart across the border, the roof across it 0.58 GSD off the other
    roofs, the orthophoto 0.12 GSD off the truth on either side and its colour 1.3 DN apart (the
    whole run on this split at 1024 px: open ground 0.04 GSD, orthophoto 0.03 GSD, 0.7 DN)."""
    import json

    import geopandas as gpd
    from scipy import ndimage
    from test_dense import _on_grid, _read

    import geoortho
    from geoortho.orthophoto.quality import geolocation_shifts, read_on_grid

    r, _ = split_on_cluster
    truth = small_survey.truth
    gsd = json.loads((truth / "survey.json").read_text())["gsd_cm_at_home_height"] / 100
    cams = gpd.read_file(r.cameras, layer="cameras")
    cams = cams[cams.registered]
    left, right = sorted((cams[cams.submodel == k].x for k in (0, 1)), key=lambda x: x.mean())
    # the cut is along x, the survey's long axis, through the middle flight line (its photos are
    # on either side of the median by their GPS noise)
    border_x = 0.5 * (left.max() + right.min())
    assert abs(left.max() - right.min()) < 2.0 and right.mean() - left.mean() > 20.0

    # depth maps at 320 px and a 15 cm DSM and orthophoto: a step or offset of a submodel shows as
    # well as at full size (a submodel's own error is the same at any size), in 21 s rather than 57
    cell_m = 0.15
    dense = geoortho.dense(r.output, small_survey.images, tmp_path / "dense.laz", max_image_size=320, workers=2)
    dem = geoortho.dem(dense.output, tmp_path / "dsm.tif", resolution_m=cell_m, max_gap_m=0)
    z, transform, crs = _read(dem.dsm)
    true_dsm = _on_grid(small_survey.dsm, transform, crs, z.shape)
    height = true_dsm - _on_grid(small_survey.dtm, transform, crs, z.shape)
    rows, cols = np.indices(z.shape)
    xs, ys = transform * (cols + 0.5, rows + 0.5)
    fx0, fy0, fx1, fy1 = json.loads((truth / "survey.json").read_text())["flight_box"]
    flown = (ys >= fy0) & (ys <= fy1)
    at_border = np.abs(xs - border_x) < 1.0
    # the case: a building across the border, GCPs beside it
    roof_cells = at_border & (height > 3)
    assert (roof_cells & (xs < border_x)).sum() * cell_m**2 > 0.5 and (roof_cells & (xs >= border_x)).sum() > 0
    gcp_x = [float(line.split()[1]) for line in (truth / "gcp_utm.txt").read_text().splitlines()[1:] if line.strip()]
    assert sum(abs(x - border_x) < 3.0 for x in gcp_x) >= 1

    dz = z - true_dsm
    # open ground: the DSM's error on either side of the border (a submodel off its neighbour is a
    # step); the roofs: the building it crosses (1 m of it on one side), against the other roofs
    ground = flown & (ndimage.maximum_filter(height, 9) < 0.2) & np.isfinite(dz)
    a = dz[ground & (xs >= border_x - 6) & (xs < border_x)]
    b = dz[ground & (xs >= border_x) & (xs < border_x + 6)]
    roof = flown & (ndimage.minimum_filter(height, 9) > 3.0) & np.isfinite(dz)
    on, off = dz[roof & (np.abs(xs - border_x) < 3)], dz[roof & (np.abs(xs - border_x) > 10)]
    assert min(a.size, b.size) > 5_000 and on.size > 300 and off.size > 3000
    steps = {
        "open": abs(float(np.median(a) - np.median(b))) / gsd,
        "roof": abs(float(np.median(on) - np.median(off))) / gsd,
    }
    assert steps["open"] <= 0.5 and steps["roof"] <= 1.0, steps  # issue 78: <= 1 GSD

    o = geoortho.ortho(
        small_survey.images, tmp_path / "o.tif", sfm=r.output, dsm=dem.dsm, resolution_m=cell_m, workers=2
    )
    tile_px = 128
    shifts = geolocation_shifts(o.output, small_survey.ortho, tile_px=tile_px)
    with rasterio.open(small_survey.ortho) as t:
        t_tr, true_rgb = t.transform, t.read((1, 2, 3)).astype(np.float32)
    offsets, colours = {}, {}
    rgb, valid = read_on_grid(o.output, small_survey.ortho)
    diff = rgb.astype(np.float32).mean(axis=0) - true_rgb.mean(axis=0)
    x = t_tr.c + (np.arange(valid.shape[1]) + 0.5) * t_tr.a
    for side in (-1, 1):
        near = [s for s in shifts if 0 < side * (t_tr.c + (s.col + tile_px / 2) * t_tr.a - border_x) < 12]
        assert len(near) >= 4, side
        offsets[side] = np.hypot(np.median([s.dx for s in near]), np.median([s.dy for s in near])) / gsd
        strip = valid & (side * (x - border_x) > 0) & (side * (x - border_x) < 6)
        colours[side] = float(np.median(diff[strip]))
    assert max(offsets.values()) <= 0.5, offsets  # issue 78: geometric offset <= 0.5 GSD
    assert abs(colours[1] - colours[-1]) <= 8.0, colours  # colour step <= 8 DN

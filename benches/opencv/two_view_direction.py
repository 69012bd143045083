"""How well can any two-view method recover the translation direction of ecm-lcd's verified loops?

A reference for the up-to-scale relative pose (docs/verification.md, "Where the unmet goals come
from"), with OpenCV (`pip install numpy opencv-python-headless`) as the independent standard. For each
loop that ecm-lcd verified without depth (a replay CSV with a pose), against the sequence's exact
ground truth, it prints the median rotation and translation-direction errors of:

  1. ecm-lcd's pose, as the CSV gives it;
  2. OpenCV on the same two frames: ORB (500 features), ratio test 0.8, the essential matrix by
     --method (RANSAC: 5-point; USAC_ACCURATE: 5-point with local optimisation and final polishing)
     at 1 px, then recoverPose;
  3. the information limit of those very points: OpenCV's inliers in the match frame lifted with the
     renderer's exact depth, projected into the query camera by the true pose (so the geometry is
     exact), Gaussian noise of --sigma px added in both frames, then the same estimation. A check
     without noise must give 0 degrees.

Usage (the renderer's camera: focal 0.82 * width, principal point at the centre):
  ecm-lcd synth -o seq --frames 600 --laps 3 --rate 5 --depth
  mkdir mono && ln -s ../seq/rgb mono/rgb && cp seq/rgb.txt seq/groundtruth.txt mono/
  ecm-lcd replay mono -o c.csv --param detector.min_score=0 --param camera.fx=262.4 \
      --param camera.fy=262.4 --param camera.cx=159.5 --param camera.cy=119.5
  python two_view_direction.py seq c.csv --sigma 0.5 --method USAC_ACCURATE
"""
import argparse
import csv

import cv2
import numpy as np


def quaternion_to_matrix(x, y, z, w):
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def read_list(path):
    """A TUM list (`stamp value...`), keyed by the stamp in milliseconds."""
    entries = {}
    for line in open(path):
        if not line.startswith('#') and line.strip():
            fields = line.split()
            entries[round(float(fields[0]) * 1000)] = fields[1:]
    return entries


def direction_error(a, b):
    return np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def rotation_error(a, b):
    return np.degrees(np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)))


def essential_pose(p1, p2, k, method, threshold):
    """R, t with x2 = R x1 + t (ecm-lcd's p_match = R p_query + t) and the inlier mask, or None."""
    try:
        e, mask = cv2.findEssentialMat(p1, p2, k, method, 0.999, threshold)
    except cv2.error:  # a degenerate sample set
        return None
    if e is None or e.shape != (3, 3):
        return None
    _, r, t, mask = cv2.recoverPose(e, p1, p2, k, mask=mask)
    return r, t.ravel(), mask.ravel() > 0


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('sequence', help='the synth folder with depth (groundtruth.txt, rgb.txt, depth.txt)')
    parser.add_argument('candidates', help="ecm-lcd's replay CSV of the same frames without depth")
    parser.add_argument('--sigma', type=float, default=0.5, help='simulated pixel noise per axis')
    parser.add_argument('--method', default='USAC_ACCURATE', help='OpenCV robust estimator')
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    method = getattr(cv2, args.method)
    truth = {s: (np.array(list(map(float, v[:3]))), quaternion_to_matrix(*map(float, v[3:7])))
             for s, v in read_list(f'{args.sequence}/groundtruth.txt').items()}
    images = {s: f'{args.sequence}/{v[0]}' for s, v in read_list(f'{args.sequence}/rgb.txt').items()}
    depths = {s: f'{args.sequence}/{v[0]}' for s, v in read_list(f'{args.sequence}/depth.txt').items()}
    first = cv2.imread(next(iter(images.values())), cv2.IMREAD_GRAYSCALE)
    height, width = first.shape
    focal = 0.82 * width
    # The renderer samples pixel x at x + 0.5 from the left edge: the centre is (width - 1) / 2 here.
    cx, cy = (width - 1) / 2, (height - 1) / 2
    k = np.array([[focal, 0, cx], [0, focal, cy], [0, 0, 1]])
    orb = cv2.ORB_create(nfeatures=500)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    errors = {name: ([], []) for name in ('ecm-lcd', 'OpenCV', 'limit', 'exact')}
    baselines = []
    for row in csv.DictReader(open(args.candidates)):
        if not row['qw']:
            continue
        query, matched = (round(float(row[c]) * 1000) for c in ('query_stamp', 'match_stamp'))
        (t_query, r_query), (t_match, r_match) = truth[query], truth[matched]
        r_true, t_true = r_match.T @ r_query, r_match.T @ (t_query - t_match)
        if np.linalg.norm(t_true) < 0.05:
            continue
        baselines.append(np.linalg.norm(t_true))
        ours = quaternion_to_matrix(*(float(row[c]) for c in ('qx', 'qy', 'qz', 'qw')))
        errors['ecm-lcd'][0].append(rotation_error(ours, r_true))
        errors['ecm-lcd'][1].append(direction_error(np.array([float(row[c]) for c in ('tx', 'ty', 'tz')]), t_true))
        gray = [cv2.imread(images[s], cv2.IMREAD_GRAYSCALE) for s in (query, matched)]
        (kq, dq), (km, dm) = (orb.detectAndCompute(g, None) for g in gray)
        if dq is None or dm is None:
            continue
        good = [p[0] for p in matcher.knnMatch(dq, dm, k=2) if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
        if len(good) < 8:
            continue
        pq = np.float64([kq[m.queryIdx].pt for m in good])
        pm = np.float64([km[m.trainIdx].pt for m in good])
        fit = essential_pose(pq, pm, k, method, 1.0)
        if fit is None:
            continue
        r, t, inliers = fit
        errors['OpenCV'][0].append(rotation_error(r, r_true))
        errors['OpenCV'][1].append(direction_error(t, t_true))
        # The same match keypoints with exact geometry, then noise.
        depth = cv2.imread(depths[matched], cv2.IMREAD_UNCHANGED).astype(np.float64) / 5000.0
        points = pm[inliers]
        pixels = np.rint(points).astype(int)
        inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < height)
        points, pixels = points[inside], pixels[inside]
        z = depth[pixels[:, 1], pixels[:, 0]]
        points, z = points[z > 0], z[z > 0]
        if len(points) < 10:
            continue
        in_match = np.column_stack([(points[:, 0] - cx) / focal * z, (points[:, 1] - cy) / focal * z, z])
        in_query = (in_match - t_true) @ r_true
        projected = np.column_stack([in_query[:, 0] / in_query[:, 2] * focal + cx,
                                     in_query[:, 1] / in_query[:, 2] * focal + cy])
        exact = essential_pose(projected, points, k, method, 0.5)
        noisy = essential_pose(projected + rng.normal(0, args.sigma, projected.shape),
                               points + rng.normal(0, args.sigma, points.shape), k, method, 3 * args.sigma)
        if exact is None or noisy is None:
            continue
        errors['exact'][1].append(direction_error(exact[1], t_true))
        errors['limit'][0].append(rotation_error(noisy[0], r_true))
        errors['limit'][1].append(direction_error(noisy[1], t_true))
    print(f'{len(baselines)} verified loops with a baseline over 5 cm; median baseline {np.median(baselines):.2f} m')
    labels = {
        'ecm-lcd': "ecm-lcd's up-to-scale pose",
        'OpenCV': f'OpenCV ORB + essential matrix ({args.method})',
        'limit': f'the same points, exact geometry + {args.sigma} px noise',
        'exact': 'the same points, exact geometry (check)',
    }
    for name, (rotation, direction) in errors.items():
        rotation_text = f'{np.median(rotation):.2f}' if rotation else '-'
        print(f'{labels[name]}: {len(direction)} pairs, median rotation {rotation_text} deg, '
              f'direction {np.median(direction):.1f} deg')


if __name__ == '__main__':
    main()

function res = hdrvdp3(task, test, reference, color_encoding, pixels_per_degree, options)
% TEST STAND-IN for HDR-VDP 3, written for hybridhdr's tests/evaluate/test_hdrvdp_bridge.py.
% It is NOT HDR-VDP: it only has the same calling convention, so the Octave/MATLAB bridge in
% hybridhdr.evaluate.metrics.hdrvdp_q can be tested without the real installation.
% Q = 10 - mean((log10(test) - log10(reference)).^2) over all pixels (luminance in cd/m2,
% floored at 1e-3), plus 0.001*pixels_per_degree so that the ppd argument is checked too.
% It errors on anything but task 'side-by-side' and colour encoding 'luminance'.
if ~strcmp(task, 'side-by-side')
  error('standin:task', 'stand-in supports task side-by-side only, got %s', task);
end
if ~strcmp(color_encoding, 'luminance')
  error('standin:enc', 'stand-in supports luminance only, got %s', color_encoding);
end
if ~isequal(size(test), size(reference))
  error('standin:size', 'test and reference sizes differ');
end
d = log10(max(test, 1e-3)) - log10(max(reference, 1e-3));
res.Q = 10 - mean(d(:).^2) + 0.001 * pixels_per_degree;
end

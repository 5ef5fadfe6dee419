function v = hdrvdp_version()
% TEST STAND-IN (see hdrvdp3.m in this folder): reports a version string that names itself.
v = '3.0.6-standin';
end

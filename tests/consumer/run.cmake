# ctest format_install_consumer: installs the vispack build to a scratch prefix, configures and
# builds tests/consumer against it (linking vispack::format_reader only), writes a sample packed
# file with format_make_sample and runs the consumer on it.
# -D BUILD_DIR=<vispack build> -D SOURCE_DIR=<vispack source> -D WORK_DIR=<scratch>
#    -D SAMPLE_TOOL=<format_make_sample> -D CXX=<compiler> [-D GENERATOR=<generator>]
#    [-D LINK_FLAGS=<flags the consumer compiles and links with: the sanitizers of a sanitized build>]
foreach(v BUILD_DIR SOURCE_DIR WORK_DIR SAMPLE_TOOL CXX)
  if(NOT DEFINED ${v})
    message(FATAL_ERROR "run.cmake needs -D ${v}=...")
  endif()
endforeach()
file(REMOVE_RECURSE "${WORK_DIR}")
file(MAKE_DIRECTORY "${WORK_DIR}")

function(step name)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
  if(NOT rc EQUAL 0)
    message(FATAL_ERROR "${name} failed (${rc}):\n${out}\n${err}")
  endif()
  set(step_output "${out}" PARENT_SCOPE)
endfunction()

step("install" ${CMAKE_COMMAND} --install "${BUILD_DIR}" --prefix "${WORK_DIR}/prefix")
set(gen_args)
if(DEFINED GENERATOR AND NOT GENERATOR STREQUAL "")
  set(gen_args -G "${GENERATOR}")
endif()
step("configure the consumer" ${CMAKE_COMMAND} -S "${SOURCE_DIR}/tests/consumer"
     -B "${WORK_DIR}/build" ${gen_args} -DCMAKE_BUILD_TYPE=Release
     -DCMAKE_CXX_COMPILER=${CXX} "-DCMAKE_PREFIX_PATH=${WORK_DIR}/prefix"
     "-DCMAKE_CXX_FLAGS=${LINK_FLAGS}" "-DCMAKE_EXE_LINKER_FLAGS=${LINK_FLAGS}")
step("build the consumer" ${CMAKE_COMMAND} --build "${WORK_DIR}/build")
step("write a sample" "${SAMPLE_TOOL}" "${WORK_DIR}/sample.vpk")
step("run the consumer" "${WORK_DIR}/build/consumer" "${WORK_DIR}/sample.vpk")
if(NOT step_output MATCHES "^consumer: 40 x 30 x 20, 3 channels, 3 levels, 96000 bytes read, ok")
  message(FATAL_ERROR "unexpected consumer output: ${step_output}")
endif()
message(STATUS "${step_output}")
file(REMOVE_RECURSE "${WORK_DIR}")
